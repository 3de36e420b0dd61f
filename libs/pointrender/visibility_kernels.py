"""Compiled image-space passes of the ``visibility`` mode (numba), bit-identical to
:func:`visibility.compose` on the numpy backend.

The array version makes some 400 passes over a view's pixels (each ``where``, ``minimum`` and
pyramid step is one), so a 256 x 256 view cost ~25 ms in memory traffic and temporaries alone.
Here the same arithmetic runs as three fused loops (surfels and footprint classes; the four
quadrant covers; visibility, pull and push) around OpenCV's min filters, which stay: they are
exact and SIMD. The four quadrant covers are kept as one four-channel image of 16-bit depth codes
(:data:`visibility.COVER_NONE`), each channel mirrored so that its quadrant window lies above-left:
one ``cv2.erode`` then dilates all four at once.

Every operation keeps the float32 rounding of the numpy expression it replaces (NEP 50: a Python
float meets a float32 array as a float32), so the tests compare the two paths exactly.
"""

from __future__ import annotations

import numpy as np

from shared.jit import AVAILABLE, kernel, numba, one_signature
from libs.pointrender.cover_codes import COVER_MAX_CODE, COVER_NONE

_INF = np.float32(np.inf)


def _classes(zmin, cnt, sp, fs_focal, rmin, rmax, lut, cls, hist):
    """Per pixel of the front layer's grid (the padded image and its guard band): the footprint
    class of its surfel (-1: none); ``hist[k]`` counts the pixels of class k."""
    hg, wg = zmin.shape
    half = np.float32(0.5)
    one = np.float32(1.0)
    for i in range(hg):
        for j in range(wg):
            z = zmin[i, j]
            if z < _INF:
                rad = np.ceil(sp[i, j] / cnt[i, j] * fs_focal / z - half)
                rad = min(max(rad, rmin), rmax)
                k = np.int32(lut[np.int64(rad + one)])
                cls[i, j] = k
                hist[k] += 1
            else:
                cls[i, j] = -1


def _bucket(cls, hist):
    """Pixels grouped by footprint class: class k is ``order[first[k]:first[k + 1]]``, each pixel as
    ``i << 16 | j`` (shifts, not a division by the width, get its row and column back)."""
    hq, wq = cls.shape
    first = np.empty(hist.shape[0] + 1, np.int64)  # not np.zeros: see kernels._front_pass
    first[0] = 0
    for k in range(hist.shape[0]):
        first[k + 1] = first[k] + hist[k]
    fill = first[:-1].copy()
    order = np.empty(first[-1], np.int64)
    for i in range(hq):
        for j in range(wq):
            k = cls[i, j]
            if k >= 0:
                order[fill[k]] = (i << 16) | j
                fill[k] += 1
    return order, first


def _mirrored_min(cov4, i, j, z):
    """Source ``z`` at pixel (i, j) into the four quadrant covers, each channel mirrored so that its
    quadrant's window lies above-left (a min: sources only ever lower a cover)."""
    ii, jj = cov4.shape[0] - 1 - i, cov4.shape[1] - 1 - j
    cov4[i, j, 0] = min(cov4[i, j, 0], z)  # (-1, -1): as is
    cov4[i, jj, 1] = min(cov4[i, jj, 1], z)  # (-1, +1): columns mirrored
    cov4[ii, j, 2] = min(cov4[ii, j, 2], z)  # (+1, -1): rows mirrored
    cov4[ii, jj, 3] = min(cov4[ii, jj, 3], z)  # (+1, +1): both


def _add_sources(cov4, order, lo, hi, zmin):
    """Sources ``order[lo:hi]`` (one footprint class) into float32 quadrant covers (their depths)."""
    for s in range(lo, hi):
        o = order[s]
        i, j = o >> 16, o & 0xFFFF
        _mirrored_min(cov4, i, j, zmin[i, j])


def _add_codes(cov4, order, lo, hi, zmin, inv_step):
    """Sources ``order[lo:hi]`` into covers of 16-bit depth codes (:data:`visibility.COVER_NONE`):
    each source's depth as ``ceil(z * inv_step)``, rounded as the array code rounds it."""
    for s in range(lo, hi):
        o = order[s]
        i, j = o >> 16, o & 0xFFFF
        code = np.uint16(min(max(np.ceil(zmin[i, j] * inv_step), np.float32(0.0)), np.float32(COVER_MAX_CODE)))
        _mirrored_min(cov4, i, j, code)


def _enclosing(q0, q1, q2, q3, step, guard, reach, far_out, near_out):
    """Per pixel of the padded image (``far_out``'s (h + 2) x (w + 2)): ``far`` and ``near2`` of
    :func:`visibility.enclosing_depth` (m, +inf: none) from the quadrant covers (-1,-1), (-1,+1),
    (+1,-1), (+1,+1) as 16-bit codes of ``step`` metres, each plane unmirrored, on the guard
    grid (the padded image at (``guard``, ``guard``)). ``far`` is the farthest cover, where a
    quadrant whose window reaches past the guard band (within ``reach`` of its edge) and found
    nothing does not count, +inf when none counts; ``near2`` the second-nearest cover, at most
    ``far``. Computed on the codes (as float32: exact; restoring is monotone, so it commutes
    with min and max), branch-free over a row (``&``/``|``, not ``and``/``or``, whose short
    circuits kept the loop from vectorising: 450 -> 80 us at 256 x 256)."""
    hp, wp = far_out.shape
    hg, wg = q0.shape
    none = np.float32(COVER_NONE)
    nil = np.float32(0.0)  # below every code (a depth beyond the near clip codes to >= 1): "does not count"
    for i in range(hp):
        ig = i + guard
        top = ig <= reach
        bottom = ig >= hg - 1 - reach
        r0, r1 = q0[ig, guard : guard + wp], q1[ig, guard : guard + wp]
        r2, r3 = q2[ig, guard : guard + wp], q3[ig, guard : guard + wp]
        fo, no = far_out[i], near_out[i]
        left_end, right_start = reach - guard, wg - 1 - reach - guard
        for j in range(wp):
            left, right = j <= left_end, j >= right_start
            a, b, c, d = np.float32(r0[j]), np.float32(r1[j]), np.float32(r2[j]), np.float32(r3[j])
            ha = nil if ((a == none) & (top | left)) else a
            hb = nil if ((b == none) & (top | right)) else b
            hc = nil if ((c == none) & (bottom | left)) else c
            hd = nil if ((d == none) & (bottom | right)) else d
            f = max(max(ha, hb), max(hc, hd))
            f = none if f == nil else f
            n2 = min(min(max(min(a, b), min(c, d)), min(max(a, b), max(c, d))), f)
            fo[j] = _INF if f == none else f * step
            no[j] = _INF if n2 == none else n2 * step


def _finish(far_img, near_img, guard, h, w, oy, ox, zmin, cnt, sz, sr, sg, sb, sl, with_slope, slope_px,
            lab_ids, lab_table, with_labels, lab_direct, tol_rel1, tol_abs, levels, offs, dims, pyr, pyr_lab,
            fill_levels, gap_levels, fill_hi, fill_lo, gap_rel, gap_scale, gap_max, out_z, out_rgb, out_lab, hole):
    """The visibility test, the pull pyramid and the push of :func:`visibility.compose`, from the
    front layer's sums (``zmin, cnt, sz, sr, sg, sb, sl`` on its grid: the padded image and its
    ``guard`` band) and each pixel's enclosing depths ``far_img`` and ``near_img`` on the padded
    image (:func:`_enclosing`).

    Labels: with ``lab_direct`` ``lab_ids`` is the label image (-1: none), else each pixel's
    nearest point id (-1: none), whose label is ``lab_table[id]``: only visible pixels read one.

    The pyramid's level 0 (the padded image, (h + 2) x (w + 2), rounded up to the coarsest cell
    and placed at (``oy``, ``ox``) of that grid) is never stored: a visible surfel weighs 1, so
    its cell is (1, mean z, mean rgb, mean z, mean z), an invisible or absent one (0, 0, 0, 0, 0,
    inf, -inf), and level 1 reads the surfels directly; the visible ones of the image go to the
    outputs in the same pass. ``pyr`` holds levels 1.. (level ``lev`` from row ``offs[lev]``),
    one row of 8 per cell (weight, sum z, sum r, g, b, nearest and farthest kept depth, spare):
    a cell's channels share a cache line. Every value is rounded as the array code rounds it
    (``mean * 1``, ``mean * 0 = 0``, sums in the order a, b, c, d)."""
    hp, wp = h + 2, w + 2
    ninf = -_INF
    zero = np.float32(0.0)
    one = np.float32(1.0)
    # Level 1 from the surfels, and the image's visible surfels (its holes marked for the push).
    h1, w1 = dims[1, 0], dims[1, 1]
    o1 = offs[1]
    inf = _INF
    # Two rows at a time (those of a row of level-1 cells): level 0 of the padded image, each
    # visible surfel's mean depth (inf: none), mean colour and label, in row buffers that stay
    # in cache; the image's own pixels go to the outputs (holes marked for the push). Then
    # level 1 from them, as the array code pulls it: a visible surfel weighs 1 and sums its mean
    # (mean * 1), an invisible one or a pixel off the padded image weighs 0 and sums 0.
    m0 = np.empty((2, wp), np.float32)
    c0 = np.empty((2, wp, 3), np.float32)
    l0 = np.empty((2, wp) if with_labels else (1, 1), np.int64)
    for I in range(h1):
        for di in range(2):
            i = 2 * I + di - oy
            if i < 0 or i >= hp:
                continue
            ig = i + guard
            inside_i = i >= 1 and i <= h
            for j in range(wp):
                jg = j + guard
                z = zmin[ig, jg]
                vis = False
                c = one
                if z < inf:
                    c = cnt[ig, jg]
                    limit = far_img[i, j] * tol_rel1 + tol_abs
                    if with_slope:
                        limit = limit + sl[ig, jg] / c * slope_px
                    vis = z <= limit
                inside = inside_i and j >= 1 and j <= w
                if vis:
                    zm, r, g, b = sz[ig, jg] / c, sr[ig, jg] / c, sg[ig, jg] / c, sb[ig, jg] / c
                    m0[di, j] = zm
                    c0[di, j, 0] = r
                    c0[di, j, 1] = g
                    c0[di, j, 2] = b
                    lab = np.int64(-1)
                    if with_labels:
                        lab = np.int64(lab_ids[ig, jg])
                        if not lab_direct and lab >= 0:
                            lab = np.int64(lab_table[lab])
                        l0[di, j] = lab
                    if inside:
                        out_z[i - 1, j - 1] = zm
                        out_rgb[0, i - 1, j - 1] = r
                        out_rgb[1, i - 1, j - 1] = g
                        out_rgb[2, i - 1, j - 1] = b
                        if with_labels:
                            out_lab[i - 1, j - 1] = lab
                else:
                    m0[di, j] = inf
                    c0[di, j, 0] = zero
                    c0[di, j, 1] = zero
                    c0[di, j, 2] = zero
                    if with_labels:
                        l0[di, j] = -1
                if inside:
                    hole[i - 1, j - 1] = not vis
        for J in range(w1):
            i, j = 2 * I - oy, 2 * J - ox
            ra = i >= 0 and i < hp
            rc = i + 1 >= 0 and i + 1 < hp
            ca = j >= 0 and j < wp
            cb = j + 1 >= 0 and j + 1 < wp
            t = o1 + I * w1 + J
            ina, inb, inc, ind = ra and ca, ra and cb, rc and ca, rc and cb
            if not ((ina and m0[0, j] < inf) or (inb and m0[0, j + 1] < inf)
                    or (inc and m0[1, j] < inf) or (ind and m0[1, j + 1] < inf)):
                # No visible surfel among its four pixels (half the cells of an agent-built map's
                # view, and the grid's margin off the padded image): what the general case
                # computes for four absent children, written directly.
                pyr[t, 0] = zero
                pyr[t, 1] = zero
                pyr[t, 2] = zero
                pyr[t, 3] = zero
                pyr[t, 4] = zero
                pyr[t, 5] = inf
                pyr[t, 6] = ninf
                if with_labels:
                    pyr_lab[t] = -1
                continue
            ma = m0[0, j] if ina else inf
            mb = m0[0, j + 1] if inb else inf
            mc = m0[1, j] if inc else inf
            md = m0[1, j + 1] if ind else inf
            va, vb, vc, vd = ma < inf, mb < inf, mc < inf, md < inf
            front = min(min(ma, mb), min(mc, md))
            thr = front * tol_rel1 + tol_abs
            ka = one if ma <= thr else zero
            kb = one if mb <= thr else zero
            kc = one if mc <= thr else zero
            kd = one if md <= thr else zero
            wa = one if va else zero
            wb = one if vb else zero
            wc = one if vc else zero
            wd = one if vd else zero
            pyr[t, 0] = wa * ka + wb * kb + wc * kc + wd * kd
            pyr[t, 1] = ((ma if va else zero) * ka + (mb if vb else zero) * kb + (mc if vc else zero) * kc
                         + (md if vd else zero) * kd)
            for ch in range(3):
                pyr[t, 2 + ch] = ((c0[0, j, ch] if va else zero) * ka + (c0[0, j + 1, ch] if vb else zero) * kb
                                  + (c0[1, j, ch] if vc else zero) * kc
                                  + (c0[1, j + 1, ch] if vd else zero) * kd)
            pyr[t, 5] = min(min(ma if ka > 0 else inf, mb if kb > 0 else inf),
                            min(mc if kc > 0 else inf, md if kd > 0 else inf))
            pyr[t, 6] = max(max(ma if (ka > 0 and va) else ninf, mb if (kb > 0 and vb) else ninf),
                            max(mc if (kc > 0 and vc) else ninf, md if (kd > 0 and vd) else ninf))
            if with_labels:
                if ka > 0 and ma == front:
                    lab = l0[0, j] if va else np.int64(-1)
                elif kb > 0 and mb == front:
                    lab = l0[0, j + 1] if vb else np.int64(-1)
                elif kc > 0 and mc == front:
                    lab = l0[1, j] if vc else np.int64(-1)
                elif kd > 0 and md == front:
                    lab = l0[1, j + 1] if vd else np.int64(-1)
                else:
                    lab = np.int64(-1)
                pyr_lab[t] = lab
    # Pull, the coarser levels: each cell keeps the children within the tolerance of its nearest
    # child. The four children (a, b over c, d) are scalars, not a small array, and each
    # channel's sum is taken in the array code's order: a, b, c, d.
    for lev in range(2, levels + 1):
        hl, wl = dims[lev, 0], dims[lev, 1]
        wc = dims[lev - 1, 1]
        o, oc = offs[lev], offs[lev - 1]
        for i in range(hl):
            row0 = oc + 2 * i * wc
            row1 = row0 + wc
            for j in range(wl):
                a, b = row0 + 2 * j, row0 + 2 * j + 1
                c, d = row1 + 2 * j, row1 + 2 * j + 1
                wa, wb, wc_, wd = pyr[a, 0], pyr[b, 0], pyr[c, 0], pyr[d, 0]
                ma = pyr[a, 1] / wa if wa > 0 else _INF
                mb = pyr[b, 1] / wb if wb > 0 else _INF
                mc = pyr[c, 1] / wc_ if wc_ > 0 else _INF
                md = pyr[d, 1] / wd if wd > 0 else _INF
                front = min(min(ma, mb), min(mc, md))
                thr = front * tol_rel1 + tol_abs
                ka = one if ma <= thr else zero
                kb = one if mb <= thr else zero
                kc = one if mc <= thr else zero
                kd = one if md <= thr else zero
                t = o + i * wl + j
                for ch in range(5):
                    acc = pyr[a, ch] * ka
                    acc = acc + pyr[b, ch] * kb
                    acc = acc + pyr[c, ch] * kc
                    acc = acc + pyr[d, ch] * kd
                    pyr[t, ch] = acc
                pyr[t, 5] = min(min(pyr[a, 5] if ka > 0 else _INF, pyr[b, 5] if kb > 0 else _INF),
                                min(pyr[c, 5] if kc > 0 else _INF, pyr[d, 5] if kd > 0 else _INF))
                pyr[t, 6] = max(max(pyr[a, 6] if ka > 0 else ninf, pyr[b, 6] if kb > 0 else ninf),
                                max(pyr[c, 6] if kc > 0 else ninf, pyr[d, 6] if kd > 0 else ninf))
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
    # Push: each image pixel without a visible surfel takes its finest acceptable ancestor.
    for i in range(1, h + 1):
        for j in range(1, w + 1):
            if not hole[i - 1, j - 1]:
                continue
            out_z[i - 1, j - 1] = zero
            for ch in range(3):
                out_rgb[ch, i - 1, j - 1] = zero
            if with_labels:
                out_lab[i - 1, j - 1] = -1
            ref, ref_lo = far_img[i, j], near_img[i, j]
            covered = ref < _INF
            iq, jq = i + oy, j + ox
            for lev in range(1, levels + 1):
                if lev > fill_levels and lev > gap_levels:
                    break
                t = offs[lev] + (iq >> lev) * dims[lev, 1] + (jq >> lev)
                wgt = pyr[t, 0]
                safe = wgt if wgt > 0 else np.float32(1.0)
                mz = pyr[t, 1] / safe
                take = False
                if lev <= fill_levels:
                    take = covered and wgt > 0 and mz <= ref * fill_hi[lev] + tol_abs
                    take = take and mz >= ref_lo * fill_lo[lev] - tol_abs
                if lev <= gap_levels and not take:
                    zl, zh = pyr[t, 5], pyr[t, 6]
                    take = (not covered) and wgt > 0 and (zh - zl <= zl * gap_rel[lev] + tol_abs)
                    take = take and zl * gap_scale[lev] <= gap_max
                if take:
                    out_z[i - 1, j - 1] = mz
                    for ch in range(3):
                        out_rgb[ch, i - 1, j - 1] = pyr[t, 2 + ch] / safe
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
    dpad = np.empty((h + 2, w + 2), np.float32)  # np.empty and fills, not np.full or np.zeros: see kernels._front_pass
    dpad[:] = _INF
    cpad = np.empty((3, h + 2, w + 2), np.float32)
    cpad[:] = zero
    for i in range(h):  # row by row and branch-free, so that the copies vectorise
        d_in, h_in, d_out = depth[i], hole[i], dpad[i + 1, 1 : w + 1]
        for j in range(w):
            d_out[j] = _INF if h_in[j] else d_in[j]
        for ch in range(3):
            c_in, c_out = rgb[ch, i], cpad[ch, i + 1, 1 : w + 1]
            for j in range(w):
                c_out[j] = c_in[j]
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
    ``renderer._images`` does with numpy, in one pass instead of four."""
    _, h, w = rgb.shape
    out = np.empty((h, w, 3), np.uint8)
    for i in range(h):
        for j in range(w):
            for ch in range(3):
                out[i, j, ch] = np.uint8(min(max(np.rint(rgb[ch, i, j]), np.float32(0.0)), np.float32(255.0)))
    return out


if AVAILABLE:
    _jit = kernel(error_model="numpy")
    _mirrored_min = numba.njit(nogil=True, cache=True, inline="always")(_mirrored_min)
    # classes: one signature too; the front layer's count and spacing arrive as strided views or copies,
    # and numba compiled it for each (the inputs typed read-only, as callers may pass read-only arrays).
    classes = one_signature(_jit(_classes), read_only=(0, 1, 2, 6))
    bucket, add_sources, add_codes = _jit(_bucket), _jit(_add_sources), _jit(_add_codes)
    # finish: one signature for its one call site, whose front layer is strided views or copies.
    enclosing, finish = _jit(_enclosing), one_signature(_jit(_finish))
    colour_filter, rgb8 = _jit(_colour_filter), _jit(_rgb8)
else:  # pragma: no cover
    classes = bucket = add_sources = add_codes = enclosing = finish = colour_filter = rgb8 = None
