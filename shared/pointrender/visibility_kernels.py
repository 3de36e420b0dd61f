"""Compiled image-space passes of the ``visibility`` mode (numba), bit-identical to
:func:`visibility.compose` on the numpy backend.

The array version makes some 400 passes over a view's pixels (each ``where``, ``minimum`` and
pyramid step is one), so a 256 x 256 view cost ~25 ms in memory traffic and temporaries alone.
Here the same arithmetic runs as three fused loops (surfels and footprint classes; the four
quadrant covers; visibility, pull and push) around OpenCV's min filters, which stay: they are
exact and SIMD. The four quadrant covers are kept as one four-channel image, each channel mirrored
so that its quadrant window lies above-left: one ``cv2.erode`` then dilates all four at once.

Every operation keeps the float32 rounding of the numpy expression it replaces (NEP 50: a Python
float meets a float32 array as a float32), so the tests compare the two paths exactly.
"""

from __future__ import annotations

import numpy as np

from shared.jit import AVAILABLE, numba

_INF = np.float32(np.inf)


def _surfels(zmin_p, cnt_p, sz_p, r_p, g_p, b_p, sp_p, lab_p, with_labels, fs_focal, rmin, rmax, lut,
             zmin, has, zmean, rgb, label, cls, hist, sl_p, with_slope, slope_px, slope_tol, guard):
    """Per pixel of the padded grid grown by its ``guard`` band (the inputs ``*_p`` and ``cls``):
    the footprint class (-1: no surfel), ``hist[k]`` counting the pixels of class k; per pixel of
    the padded grid (the outputs, ``guard`` in from the inputs' border): the surfel (zmin, has,
    mean depth, mean colour, label, and with ``with_slope`` the slope part of its visibility
    tolerance). (The array code pads these images further for the pyramid; the extra pixels hold
    no surfel, and :func:`_finish` reads them as such.)"""
    hg, wg = zmin_p.shape
    hp, wp = zmin.shape
    half = np.float32(0.5)
    one = np.float32(1.0)
    for i in range(hg):
        for j in range(wg):
            z = zmin_p[i, j]
            if z < _INF:
                c = cnt_p[i, j]
                sp = sp_p[i, j] / c
                rad = np.ceil(sp * fs_focal / z - half)
                rad = min(max(rad, rmin), rmax)
                k = np.int32(lut[np.int64(rad + one)])
                cls[i, j] = k
                hist[k] += 1
            else:
                cls[i, j] = -1
    for i in range(hp):
        for j in range(wp):
            ig, jg = i + guard, j + guard
            z = zmin_p[ig, jg]
            h = z < _INF
            c = cnt_p[ig, jg] if h else one
            zmin[i, j] = z
            has[i, j] = h
            zmean[i, j] = sz_p[ig, jg] / c
            rgb[0, i, j] = r_p[ig, jg] / c
            rgb[1, i, j] = g_p[ig, jg] / c
            rgb[2, i, j] = b_p[ig, jg] / c
            if with_labels:
                label[i, j] = lab_p[ig, jg]
            if with_slope:
                slope_tol[i, j] = sl_p[ig, jg] / c * slope_px


def _bucket(cls, hist):
    """Pixel ids (i * wq + j) grouped by footprint class: class k is ``order[first[k]:first[k + 1]]``."""
    hq, wq = cls.shape
    first = np.zeros(hist.shape[0] + 1, np.int64)
    for k in range(hist.shape[0]):
        first[k + 1] = first[k] + hist[k]
    fill = first[:-1].copy()
    order = np.empty(first[-1], np.int64)
    for i in range(hq):
        for j in range(wq):
            k = cls[i, j]
            if k >= 0:
                order[fill[k]] = i * wq + j
                fill[k] += 1
    return order, first


def _add_sources(cov4, order, lo, hi, zmin):
    """Sources ``order[lo:hi]`` (one footprint class) into the four mirrored quadrant covers (min)."""
    hq, wq = zmin.shape
    for s in range(lo, hi):
        i, j = order[s] // wq, order[s] % wq
        z = zmin[i, j]
        ii, jj = hq - 1 - i, wq - 1 - j
        cov4[i, j, 0] = min(cov4[i, j, 0], z)  # (-1, -1): as is
        cov4[i, jj, 1] = min(cov4[i, jj, 1], z)  # (-1, +1): columns mirrored
        cov4[ii, j, 2] = min(cov4[ii, j, 2], z)  # (+1, -1): rows mirrored
        cov4[ii, jj, 3] = min(cov4[ii, jj, 3], z)  # (+1, +1): both


def _finish(cov4, guard, reach, h, w, hq, wq, oy, ox, zmin, has, zmean, rgb, label, with_labels, tol_rel1, tol_abs, slope_tol,
            with_slope, levels, offs, dims,
            pyr, pyr_lab, fill_levels, gap_levels, fill_hi, fill_lo, gap_rel, gap_scale, gap_max,
            out_z, out_rgb, out_lab, hole):
    """Enclosing depths, the visibility test, the pull pyramid and the push, as the array code.

    The surfel images span the padded grid ``zmin.shape``, the covers that grid grown by its
    ``guard`` band; the pyramid spans ``hq`` x ``wq`` (the padded grid rounded up to its coarsest
    cell, placed at (``oy``, ``ox``) of it), whose extra pixels hold no surfel."""
    hp, wp = zmin.shape
    hg, wg = cov4.shape[0], cov4.shape[1]
    ninf = -_INF
    zero = np.float32(0.0)
    # far / near2 per pixel of the padded grid, and level 0 of the pyramid (the visible surfels;
    # channels: weight, sum z, sum r, g, b, zlo, zhi), in one pass.
    far = np.empty((hp, wp), np.float32)
    near2 = np.empty((hp, wp), np.float32)
    for iq in range(hq):
        for jq in range(wq):
            t = iq * wq + jq
            i, j = iq - oy, jq - ox
            if i < 0 or j < 0 or i >= hp or j >= wp:
                for ch in range(5):
                    pyr[ch, t] = zero
                pyr[5, t] = _INF
                pyr[6, t] = ninf
                if with_labels:
                    pyr_lab[t] = -1
                continue
            ig, jg = i + guard, j + guard
            ii, jj = hg - 1 - ig, wg - 1 - jg
            l0 = cov4[ig, jg, 0]
            l1 = cov4[ig, jj, 1]
            l2 = cov4[ii, jg, 2]
            l3 = cov4[ii, jj, 3]
            # A quadrant that reaches past the guard band and found nothing does not count.
            top, left = ig <= reach, jg <= reach
            bottom, right = ig >= hg - 1 - reach, jg >= wg - 1 - reach
            f = ninf
            f = max(f, ninf if (l0 == _INF and (top or left)) else l0)
            f = max(f, ninf if (l1 == _INF and (top or right)) else l1)
            f = max(f, ninf if (l2 == _INF and (bottom or left)) else l2)
            f = max(f, ninf if (l3 == _INF and (bottom or right)) else l3)
            if f == ninf:
                f = _INF
            n2 = min(max(min(l0, l1), min(l2, l3)), min(max(l0, l1), max(l2, l3)))
            far[i, j] = f
            near2[i, j] = min(n2, f)
            limit = f * tol_rel1 + tol_abs
            if with_slope:
                limit = limit + slope_tol[i, j]
            vis = has[i, j] and zmin[i, j] <= limit
            wgt = np.float32(1.0) if vis else zero
            zm = zmean[i, j]
            pyr[0, t] = wgt
            pyr[1, t] = zm * wgt
            pyr[2, t] = rgb[0, i, j] * wgt
            pyr[3, t] = rgb[1, i, j] * wgt
            pyr[4, t] = rgb[2, i, j] * wgt
            pyr[5, t] = zm if vis else _INF
            pyr[6, t] = zm if vis else ninf
            if with_labels:
                pyr_lab[t] = label[i, j] if vis else -1
    # Pull: each coarser cell keeps the children within the tolerance of its nearest child.
    # The four children (a, b over c, d) are scalars, not a small array, and each channel's sum
    # is taken in the array code's order: a, b, c, d.
    one = np.float32(1.0)
    for lev in range(1, levels + 1):
        hl, wl = dims[lev, 0], dims[lev, 1]
        wc = dims[lev - 1, 1]
        o, oc = offs[lev], offs[lev - 1]
        for i in range(hl):
            row0 = oc + 2 * i * wc
            row1 = row0 + wc
            for j in range(wl):
                a, b = row0 + 2 * j, row0 + 2 * j + 1
                c, d = row1 + 2 * j, row1 + 2 * j + 1
                wa, wb, wc_, wd = pyr[0, a], pyr[0, b], pyr[0, c], pyr[0, d]
                ma = pyr[1, a] / wa if wa > 0 else _INF
                mb = pyr[1, b] / wb if wb > 0 else _INF
                mc = pyr[1, c] / wc_ if wc_ > 0 else _INF
                md = pyr[1, d] / wd if wd > 0 else _INF
                front = min(min(ma, mb), min(mc, md))
                thr = front * tol_rel1 + tol_abs
                ka = one if ma <= thr else zero
                kb = one if mb <= thr else zero
                kc = one if mc <= thr else zero
                kd = one if md <= thr else zero
                t = o + i * wl + j
                for ch in range(5):
                    acc = pyr[ch, a] * ka
                    acc = acc + pyr[ch, b] * kb
                    acc = acc + pyr[ch, c] * kc
                    acc = acc + pyr[ch, d] * kd
                    pyr[ch, t] = acc
                pyr[5, t] = min(min(pyr[5, a] if ka > 0 else _INF, pyr[5, b] if kb > 0 else _INF),
                                min(pyr[5, c] if kc > 0 else _INF, pyr[5, d] if kd > 0 else _INF))
                pyr[6, t] = max(max(pyr[6, a] if ka > 0 else ninf, pyr[6, b] if kb > 0 else ninf),
                                max(pyr[6, c] if kc > 0 else ninf, pyr[6, d] if kd > 0 else ninf))
                if with_labels:
                    # The label of the nearest kept child, the first in that order on ties.
                    if ka > 0 and ma == front:
                        lab = pyr_lab[a]
                    elif kb > 0 and mb == front:
                        lab = pyr_lab[b]
                    elif kc > 0 and mc == front:
                        lab = pyr_lab[c]
                    elif kd > 0 and md == front:
                        lab = pyr_lab[d]
                    else:
                        lab = -1
                    pyr_lab[t] = lab
    # Push: each crop pixel without a visible surfel takes its finest acceptable ancestor.
    for i in range(1, h + 1):
        for j in range(1, w + 1):
            iq, jq = i + oy, j + ox
            t0 = iq * wq + jq
            if pyr[0, t0] > 0:
                out_z[i - 1, j - 1] = zmean[i, j]
                for ch in range(3):
                    out_rgb[ch, i - 1, j - 1] = rgb[ch, i, j]
                if with_labels:
                    out_lab[i - 1, j - 1] = label[i, j]
                hole[i - 1, j - 1] = False
                continue
            out_z[i - 1, j - 1] = zero
            for ch in range(3):
                out_rgb[ch, i - 1, j - 1] = zero
            if with_labels:
                out_lab[i - 1, j - 1] = -1
            hole[i - 1, j - 1] = True
            ref, ref_lo = far[i, j], near2[i, j]
            covered = ref < _INF
            for lev in range(1, levels + 1):
                if lev > fill_levels and lev > gap_levels:
                    break
                t = offs[lev] + (iq >> lev) * dims[lev, 1] + (jq >> lev)
                wgt = pyr[0, t]
                safe = wgt if wgt > 0 else np.float32(1.0)
                mz = pyr[1, t] / safe
                take = False
                if lev <= fill_levels:
                    take = covered and wgt > 0 and mz <= ref * fill_hi[lev] + tol_abs
                    take = take and mz >= ref_lo * fill_lo[lev] - tol_abs
                if lev <= gap_levels and not take:
                    zl, zh = pyr[5, t], pyr[6, t]
                    take = (not covered) and wgt > 0 and (zh - zl <= zl * gap_rel[lev] + tol_abs)
                    take = take and zl * gap_scale[lev] <= gap_max
                if take:
                    out_z[i - 1, j - 1] = mz
                    for ch in range(3):
                        out_rgb[ch, i - 1, j - 1] = pyr[2 + ch, t] / safe
                    if with_labels:
                        out_lab[i - 1, j - 1] = pyr_lab[t]
                    hole[i - 1, j - 1] = False
                    break


def _colour_filter(rgb, depth, hole, rel, taps):
    """:func:`visibility.colour_filter`, same taps, order and float32 rounding. The images are
    read through a one-pixel ring (depth +inf, colour 0; holes +inf too) so that the tap loop
    needs no bounds tests: a ring or hole tap fails the depth test and adds colour * 0 = +0,
    which leaves a sum as it was, as skipping it does."""
    h, w = depth.shape
    zero = np.float32(0.0)
    dpad = np.full((h + 2, w + 2), _INF, np.float32)
    cpad = np.zeros((3, h + 2, w + 2), np.float32)
    for i in range(h):
        for j in range(w):
            if not hole[i, j]:
                dpad[i + 1, j + 1] = depth[i, j]
            for ch in range(3):
                cpad[ch, i + 1, j + 1] = rgb[ch, i, j]
    out = np.empty_like(rgb)
    one = np.float32(1.0)
    k0, k1, k2, k3, k4, k5, k6, k7, k8 = taps[0], taps[1], taps[2], taps[3], taps[4], taps[5], taps[6], taps[7], taps[8]
    # Branch-free over a row (a hole pixel computes garbage from d = +inf and is zeroed at the
    # end), the nine taps written out in their fixed order: the row loop vectorises.
    for i in range(h):
        for j in range(w):
            d = dpad[i + 1, j + 1]
            tol = d * rel
            a0 = a1 = a2 = ws = zero
            wt = k0 if abs(dpad[i + 0, j + 0] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 0, j + 0] * wt
            a1 = a1 + cpad[1, i + 0, j + 0] * wt
            a2 = a2 + cpad[2, i + 0, j + 0] * wt
            wt = k1 if abs(dpad[i + 0, j + 1] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 0, j + 1] * wt
            a1 = a1 + cpad[1, i + 0, j + 1] * wt
            a2 = a2 + cpad[2, i + 0, j + 1] * wt
            wt = k2 if abs(dpad[i + 0, j + 2] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 0, j + 2] * wt
            a1 = a1 + cpad[1, i + 0, j + 2] * wt
            a2 = a2 + cpad[2, i + 0, j + 2] * wt
            wt = k3 if abs(dpad[i + 1, j + 0] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 1, j + 0] * wt
            a1 = a1 + cpad[1, i + 1, j + 0] * wt
            a2 = a2 + cpad[2, i + 1, j + 0] * wt
            wt = k4 if abs(dpad[i + 1, j + 1] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 1, j + 1] * wt
            a1 = a1 + cpad[1, i + 1, j + 1] * wt
            a2 = a2 + cpad[2, i + 1, j + 1] * wt
            wt = k5 if abs(dpad[i + 1, j + 2] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 1, j + 2] * wt
            a1 = a1 + cpad[1, i + 1, j + 2] * wt
            a2 = a2 + cpad[2, i + 1, j + 2] * wt
            wt = k6 if abs(dpad[i + 2, j + 0] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 2, j + 0] * wt
            a1 = a1 + cpad[1, i + 2, j + 0] * wt
            a2 = a2 + cpad[2, i + 2, j + 0] * wt
            wt = k7 if abs(dpad[i + 2, j + 1] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 2, j + 1] * wt
            a1 = a1 + cpad[1, i + 2, j + 1] * wt
            a2 = a2 + cpad[2, i + 2, j + 1] * wt
            wt = k8 if abs(dpad[i + 2, j + 2] - d) <= tol else zero
            ws = ws + wt
            a0 = a0 + cpad[0, i + 2, j + 2] * wt
            a1 = a1 + cpad[1, i + 2, j + 2] * wt
            a2 = a2 + cpad[2, i + 2, j + 2] * wt
            s = ws if ws > 0 else one
            hl = hole[i, j]
            out[0, i, j] = zero if hl else a0 / s
            out[1, i, j] = zero if hl else a1 / s
            out[2, i, j] = zero if hl else a2 / s
    return out


def _rgb8(rgb):
    """(3, H, W) float32 -> (H, W, 3) uint8, rounded half to even and clipped: what
    ``splat._images`` does with numpy, in one pass instead of four."""
    _, h, w = rgb.shape
    out = np.empty((h, w, 3), np.uint8)
    for i in range(h):
        for j in range(w):
            for ch in range(3):
                out[i, j, ch] = np.uint8(min(max(np.rint(rgb[ch, i, j]), np.float32(0.0)), np.float32(255.0)))
    return out


if AVAILABLE:
    _jit = numba.njit(nogil=True, cache=True, error_model="numpy")
    surfels, bucket, add_sources, finish = _jit(_surfels), _jit(_bucket), _jit(_add_sources), _jit(_finish)
    colour_filter, rgb8 = _jit(_colour_filter), _jit(_rgb8)
else:  # pragma: no cover
    surfels = bucket = add_sources = finish = colour_filter = rgb8 = None
