"""Truncated signed distance fusion of a noisy-depth region (``RgbdConfig.fusion`` "tsdf", issue 33).

The voxel fusion (``regional.py``) keeps the centroid of the points that fall into each voxel: a
surface's noisy draws from every frame that saw it land in two or three voxels along its normal, and
the centroid averages only within one of them, so the map holds a slab of points around each wall.
A truncated signed distance volume (Curless and Levoy 1996, "A volumetric method for building complex
models from range images"; KinectFusion's projective form) averages, per voxel, the signed distance
to the surface each frame measured along its ray: every look at a surface votes on where that one
surface is, and the fused surface is the zero crossing between neighbouring voxels, one sheet of
points whose error shrinks with the number of looks instead of a slab as thick as the noise.

* Each valid pixel of depth ``d`` updates the voxels its ray crosses from ``d - front`` to
  ``d + back``: the signed distance of the voxel's centre (``d`` less the centre's depth in that
  camera), clipped to the band, weighted by ``1 / sigma^2`` (the frame's declared sigma at ``d``, not
  below ``sigma_floor_m``): a look from 50 cm outweighs one from 3 m by hundreds, so a far look only
  decides where no near look reached (the voxel fusion needed two tiers for that). The band in front
  is ``max(trunc_min_m, trunc_sigmas * sigma)``, so a noisy far draw still reaches the voxels at the
  true surface; behind it at most ``trunc_back_m``, so a look at one face of a 10 cm wall never writes
  "inside" into the other face's voxels.
* Colour, semantic label and the view direction are kept per voxel from the pixels whose surface lies
  in it (within half a voxel of its centre; within a whole one, a far-face voxel of a 10 cm wall took the
  near face's colour from its noisiest draws): colour and label weighted as the distance is, the view
  direction as
  the voxel fusion's (the plain mean of the unit vectors towards the cameras: ``PointCloud.view_dirs``).
  The label is a weighted streaming majority (Boyer-Moore: the label that holds more than half of the
  weight wins; otherwise one of the contenders).
* The cloud is the zero crossings between each voxel and its +x, +y, +z neighbour, both seen at
  least ``min_updates`` times, with distances no more than ``crossing_max_vox`` voxels apart (a jump
  between a band's far end and another surface's is no surface), placed by linear interpolation and
  carrying the attributes of the voxel nearer the surface (the view direction: the mean of both);
  with ``fill_m``, crossings seen less often are kept where no better one lies that close.
* A pixel is one ray, or (``max_sub_rays`` > 1) up to that many a side where it is wider than a voxel.

The volume lives in an open-addressing hash of packed voxel keys (``kernels``' table and key packing),
so nothing is sized by the region's bounding box.

Two paths with identical results (tests compare them bit for bit): the compiled loops (numba) and the
array code, its fallback (``RgbdConfig.kernel`` "numpy", or numba missing), which takes a frame's rays
at once: every pixel's band as one (pixel, sub-ray, step) grid of samples, the voxels found in a sorted
index of the keys instead of the hash. The streaming order survives: new voxels are numbered in the
order the loops meet them, ``np.add.at`` adds a frame's samples to each voxel's sums one by one in
that order, and the label majority, whose result depends on it, steps through each voxel's labels rank
by rank (one step per rank for every voxel that saw two labels in the frame, or a label other than the
one it holds; the others add their weights at once).
"""

from __future__ import annotations

import math

import numpy as np

from shared.cloud import PointCloud, quantise_view_dirs
from shared.jit import AVAILABLE, kernel

from . import kernels
from .kernels import AXIS_BITS, AXIS_HALF, LABEL_MAX
from .voxel import pack_cells, unpack_keys

# Columns of a voxel's row: weighted distance sum, weight sum, weighted colour sums, updates, label
# slot (label + 1, 0: none) and its weighted majority counter, view-vector sums and their count, and
# the weight of the colour sums.
_SDF, _W, _RGB, _N, _LAB, _LABW, _VIEW, _VN, _CW = 0, 1, 2, 5, 6, 7, 8, 11, 12
_ROW = 13


def _lookup(table, shift, key):
    """Entry id of ``key`` in the table, or -1."""
    mask = table.shape[0] - 1
    s = kernels._slot(key, shift)
    while True:
        k = table[s, 0]
        if k == key:
            return table[s, 1]
        if k == -1:
            return -1
        s = (s + 1) & mask


def _integrate(depth, rgb, sem, labelled, stride, rays, backs, pitch, m, dmin, dmax, voxel, rel, sigma_floor,
               trunc_min, trunc_sigmas, trunc_back, max_sub, table, shift, keys, rows, n):
    """Add one frame to the volume; returns (entries, status, pixels integrated): status 1 when a voxel
    falls outside the packable range (nothing more is added then). ``pitch``: the (strided) pixel's width and height in
    unit-depth rays. The caller guarantees room for every voxel the frame's bands can reach."""
    h = depth.shape[0]
    w = depth.shape[1]
    hs = (h + stride - 1) // stride
    ws = (w + stride - 1) // stride
    half = np.int64(AXIS_HALF)
    inv = 1.0 / voxel
    m00, m01, m02 = m[0, 0], m[0, 1], m[0, 2]
    m10, m11, m12 = m[1, 0], m[1, 1], m[1, 2]
    m20, m21, m22 = m[2, 0], m[2, 1], m[2, 2]
    used = 0
    for i in range(hs):
        r = i * stride
        for j in range(ws):
            c = j * stride
            d = np.float64(depth[r, c])
            if not (d > dmin and d < dmax):  # NaN compares False
                continue
            q = i * ws + j
            used += 1
            rx = np.float64(rays[q, 0])
            ry = np.float64(rays[q, 1])
            sigma = max(rel * d * d, sigma_floor)
            wt = 1.0 / (sigma * sigma)
            front = max(trunc_min, trunc_sigmas * sigma)
            back = min(front, trunc_back)
            # Steps of half a voxel along the ray (in depth: the ray's length per unit depth).
            dz = 0.5 * voxel / math.sqrt(rx * rx + ry * ry + 1.0)
            steps = int((front + back) / dz) + 1
            vx = m00 * backs[q, 0] + m01 * backs[q, 1] + m02 * backs[q, 2]
            vy = m10 * backs[q, 0] + m11 * backs[q, 1] + m12 * backs[q, 2]
            vz = m20 * backs[q, 0] + m21 * backs[q, 1] + m22 * backs[q, 2]
            # A pixel wider than a voxel at its depth (3 cm at 2.4 m, 128 px over 90 deg) walks that many
            # rays across its footprint, or the voxels between two pixels' rays would never be updated and
            # a far-seen wall would have no neighbouring voxels to find its zero crossing between.
            sub = min(max_sub, int(math.ceil(d * max(pitch[0], pitch[1]) / voxel)))
            for t in range(sub * sub):
                ox_ = ((t % sub) + 0.5) / sub - 0.5
                oy_ = ((t // sub) + 0.5) / sub - 0.5
                n, status = _walk(rx + ox_ * pitch[0], ry + oy_ * pitch[1], d, front, back, dz, steps, wt, voxel,
                                  inv, half, m, rgb, sem, labelled, r, c, vx, vy, vz, table, shift, keys, rows, n)
                if status:
                    return n, status, used
    return n, 0, used


def _walk(rx, ry, d, front, back, dz, steps, wt, voxel, inv, half, m, rgb, sem, labelled, r, c, vx, vy, vz,
          table, shift, keys, rows, n):
    """One ray's band (direction ``(rx, ry, 1)`` in the camera, the pixel's depth ``d``) into the volume;
    returns (entries, status), status as ``_integrate``'s."""
    m00, m01, m02, m03 = m[0, 0], m[0, 1], m[0, 2], m[0, 3]
    m10, m11, m12, m13 = m[1, 0], m[1, 1], m[1, 2], m[1, 3]
    m20, m21, m22, m23 = m[2, 0], m[2, 1], m[2, 2], m[2, 3]
    last = np.int64(-1)
    for s in range(steps + 1):
        z = d - front + s * dz
        if z <= 0.0:
            continue
        xc = rx * z
        yc = ry * z
        cx = np.int64(math.floor((m00 * xc + m01 * yc + m02 * z + m03) * inv))
        cy = np.int64(math.floor((m10 * xc + m11 * yc + m12 * z + m13) * inv))
        cz = np.int64(math.floor((m20 * xc + m21 * yc + m22 * z + m23) * inv))
        if (cx < -half) | (cx >= half - 1) | (cy < -half) | (cy >= half - 1) | (cz < -half) | (cz >= half - 1):
            return n, 1
        key = ((cx + half) << (2 * AXIS_BITS)) | ((cy + half) << AXIS_BITS) | (cz + half)
        if key == last:
            continue
        last = key
        # The centre's depth in this camera: its offset from the camera along the optical axis.
        ox = (cx + 0.5) * voxel - m03
        oy = (cy + 0.5) * voxel - m13
        oz = (cz + 0.5) * voxel - m23
        sdf = d - (m02 * ox + m12 * oy + m22 * oz)
        if sdf < -back:
            continue
        if sdf > front:
            sdf = front
        e, n = kernels._find_or_add(table, shift, key, n, keys)
        rows[e, _SDF] += wt * sdf
        rows[e, _W] += wt
        rows[e, _N] += 1.0
        if abs(sdf) < 0.5 * voxel:  # this pixel's surface lies in this voxel
            rows[e, _RGB] += wt * np.float64(rgb[r, c, 0])
            rows[e, _RGB + 1] += wt * np.float64(rgb[r, c, 1])
            rows[e, _RGB + 2] += wt * np.float64(rgb[r, c, 2])
            rows[e, _CW] += wt
            rows[e, _VIEW] += vx
            rows[e, _VIEW + 1] += vy
            rows[e, _VIEW + 2] += vz
            rows[e, _VN] += 1.0
            if labelled:
                lab = np.int64(sem[r, c])
                if lab >= 0 and lab <= LABEL_MAX:
                    cur = rows[e, _LAB]
                    if cur == np.float64(lab + 1):
                        rows[e, _LABW] += wt
                    elif rows[e, _LABW] >= wt:
                        rows[e, _LABW] -= wt
                    else:
                        rows[e, _LAB] = np.float64(lab + 1)
                        rows[e, _LABW] = wt - rows[e, _LABW]
    return n, 0


def _extract(keys, rows, n, table, shift, voxel, min_updates, crossing_max, xyz, rgb, lab, view, support):
    """The zero crossings between each voxel and its +x, +y, +z neighbour into the output arrays
    (room for 3 n), each with the fewer updates of its two voxels (``support``); returns how many."""
    half = np.int64(AXIS_HALF)
    mask = np.int64((1 << AXIS_BITS) - 1)
    steps = (np.int64(1) << (2 * AXIS_BITS), np.int64(1) << AXIS_BITS, np.int64(1))
    out = 0
    for a in range(n):
        if rows[a, _N] < min_updates:
            continue
        ta = rows[a, _SDF] / rows[a, _W]
        key = keys[a]
        base_x = ((key >> (2 * AXIS_BITS)) & mask) - half
        base_y = ((key >> AXIS_BITS) & mask) - half
        base_z = (key & mask) - half
        for axis in range(3):
            b = _lookup(table, shift, key + steps[axis])
            if b < 0 or rows[b, _N] < min_updates:
                continue
            tb = rows[b, _SDF] / rows[b, _W]
            if (ta >= 0.0) == (tb >= 0.0) or abs(ta - tb) > crossing_max:
                continue
            f = ta / (ta - tb)
            px = (base_x + 0.5) * voxel
            py = (base_y + 0.5) * voxel
            pz = (base_z + 0.5) * voxel
            if axis == 0:
                px += f * voxel
            elif axis == 1:
                py += f * voxel
            else:
                pz += f * voxel
            # Attributes of the voxel nearer the surface, the other's where it saw no surface pixel.
            near, other = (a, b) if abs(ta) <= abs(tb) else (b, a)
            src = near if rows[near, _CW] > 0.0 else other
            if rows[src, _CW] <= 0.0:
                continue
            xyz[out, 0] = px
            xyz[out, 1] = py
            xyz[out, 2] = pz
            for k in range(3):
                rgb[out, k] = rows[src, _RGB + k] / rows[src, _CW]
            lsrc = near if rows[near, _LAB] > 0.0 else other
            lab[out] = np.int64(rows[lsrc, _LAB]) - 1
            vn = rows[a, _VN] + rows[b, _VN]
            for k in range(3):
                view[out, k] = (rows[a, _VIEW + k] + rows[b, _VIEW + k]) / vn
            support[out] = min(rows[a, _N], rows[b, _N])
            out += 1
    return out


if AVAILABLE:
    _jit = kernel(error_model="numpy")
    _lookup = _jit(_lookup)
    _walk = _jit(_walk)
    integrate = _jit(_integrate)
    extract = _jit(_extract)
else:  # pragma: no cover
    integrate = extract = None


# The array twins: a frame's pixels in chunks of about this many samples (pixel x sub-ray x step), so
# that a 256 x 256 frame with 3 x 3 sub-rays does not hold its whole band in memory at once.
_CHUNK_SAMPLES = 1 << 20


class _SortedIndex:
    """The array path's map of packed voxel keys to entry ids: the keys ascending, with their ids.

    A frame adds its new keys in one merge (a copy of the index: linear in the volume, once a frame),
    where the compiled path probes its hash key by key."""

    def __init__(self):
        self.keys = np.empty(0, np.int64)
        self.ids = np.empty(0, np.int64)

    def find(self, keys: np.ndarray) -> np.ndarray:
        """Entry id of each key, -1 where it is not in the index."""
        if len(self.keys) == 0:
            return np.full(len(keys), -1, np.int64)
        at = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        return np.where(self.keys[at] == keys, self.ids[at], -1)

    def insert(self, keys: np.ndarray, ids: np.ndarray) -> None:
        """Add ``keys`` (ascending, none in the index yet) with their ``ids``."""
        pos = np.searchsorted(self.keys, keys)
        self.keys = np.insert(self.keys, pos, keys)
        self.ids = np.insert(self.ids, pos, ids)


def _integrate_array(vol: TsdfVolume, depth, rgb, sem, stride, rays, backs, pitch, m, dmax, rel):
    """``_integrate``'s twin on ``vol``'s arrays (its ``index`` for the table); returns (status, pixels
    integrated). Status 1 leaves the frame out whole (the compiled loop stops where it met the voxel):
    the caller raises either way."""
    voxel = vol.voxel_m
    dall = np.asarray(depth[::stride, ::stride], np.float64).reshape(-1)
    q = np.flatnonzero((dall > vol.dmin) & (dall < dmax))  # NaN compares False
    if len(q) == 0:
        return 0, 0
    # float64 throughout, each expression associated as the loop's, so every sample lands in the same
    # voxel with the same distance.
    d = dall[q]
    rx, ry = rays[q, 0].astype(np.float64), rays[q, 1].astype(np.float64)
    sigma = np.maximum(rel * d * d, vol.sigma_floor_m)
    wt = 1.0 / (sigma * sigma)
    front = np.maximum(vol.trunc_min_m, vol.trunc_sigmas * sigma)
    back = np.minimum(front, vol.trunc_back_m)
    dz = 0.5 * voxel / np.sqrt(rx * rx + ry * ry + 1.0)
    steps = ((front + back) / dz).astype(np.int64) + 1
    b = backs[q].astype(np.float64)
    view = np.stack([m[k, 0] * b[:, 0] + m[k, 1] * b[:, 1] + m[k, 2] * b[:, 2] for k in range(3)], axis=1)
    sub = np.minimum(vol.max_sub_rays, np.ceil(d * max(pitch[0], pitch[1]) / voxel).astype(np.int64))
    colour = rgb[::stride, ::stride].reshape(-1, 3)[q]
    lab = sem[::stride, ::stride].reshape(-1)[q].astype(np.int64) if vol.labelled else None
    # The pixels in chunks, in order: each chunk's samples are added before the next chunk's.
    per_pixel = (sub * sub) * (steps + 1)
    ends = np.searchsorted(np.cumsum(per_pixel), np.arange(1, per_pixel.sum() // _CHUNK_SAMPLES + 1) * _CHUNK_SAMPLES)
    for lo, hi in zip(np.r_[0, ends], np.r_[ends, len(q)]):
        if hi <= lo:
            continue
        sl = slice(lo, hi)
        p = _band_samples(vol, d[sl], rx[sl], ry[sl], front[sl], back[sl], dz[sl], steps[sl], sub[sl], pitch, m)
        if p is None:
            return 1, 0
        pix, key, sdf = p
        _accumulate(vol, key, sdf, pix + lo, wt, colour, view, lab)
    return 0, len(q)


def _band_samples(vol: TsdfVolume, d, rx, ry, front, back, dz, steps, sub, pitch, m):
    """The updates of these pixels' bands in the loops' order (pixel, sub-ray, step): (pixel, packed voxel
    key, clipped signed distance) of each, the loop's repeated voxels and far-behind samples left out; None
    when a voxel falls outside the packable range."""
    half = AXIS_HALF
    t_n = int((sub * sub).max())
    s_n = int(steps.max()) + 1
    t = np.arange(t_n)[None, :]
    s = np.arange(s_n)[None, :]
    # (P, T): each sub-ray's direction; (P, S): each step's depth, rising along the ray.
    subf = np.maximum(sub, 1)[:, None]
    srx = rx[:, None] + (((t % subf) + 0.5) / subf - 0.5) * pitch[0]
    sry = ry[:, None] + (((t // subf) + 0.5) / subf - 0.5) * pitch[1]
    z = (d - front)[:, None] + s * dz[:, None]
    # A ray's samples are one run of steps: those with z <= 0 come first, those past its band last.
    first = ((z <= 0.0) & (s <= steps[:, None])).sum(axis=1)
    rp, rt = np.nonzero(t < (sub * sub)[:, None])  # the rays, in the loops' order
    count = np.maximum(steps - first + 1, 0)[rp]
    ray = np.repeat(np.arange(len(rp)), count)  # each sample's ray, samples in the loops' order
    si = first[rp][ray] + (np.arange(len(ray)) - np.repeat(np.cumsum(count) - count, count))
    pix = rp[ray]
    z = np.take(z.reshape(-1), pix * s_n + si)
    xc, yc = np.take(srx[rp, rt], ray) * z, np.take(sry[rp, rt], ray) * z
    cell = []
    for k in range(3):  # m[k, 0] * xc + m[k, 1] * yc + m[k, 2] * z + m[k, 3], in place
        p = m[k, 0] * xc
        p += m[k, 1] * yc
        p += m[k, 2] * z
        p += m[k, 3]
        p *= 1.0 / vol.voxel_m
        cell.append(np.floor(p, out=p).astype(np.int64))
    if any(len(c) and (c.min() < -half or c.max() >= half - 1) for c in cell):
        return None
    key = pack_cells(cell[0] + half, cell[1] + half, cell[2] + half)
    # A ray's consecutive samples in one voxel update it once.
    keep = np.ones(len(key), bool)
    keep[1:] = (ray[1:] != ray[:-1]) | (key[1:] != key[:-1])
    pix, key, cell = pix[keep], key[keep], [c[keep] for c in cell]
    centre = [(c + 0.5) * vol.voxel_m - m[k, 3] for k, c in enumerate(cell)]
    sdf = d[pix] - (m[0, 2] * centre[0] + m[1, 2] * centre[1] + m[2, 2] * centre[2])
    keep = ~(sdf < -back[pix])
    pix, sdf = pix[keep], sdf[keep]
    return pix, key[keep], np.minimum(sdf, front[pix])


def _accumulate(vol: TsdfVolume, key, sdf, pix, wt, rgb, view, lab):
    """Add samples (in the loops' order; ``pix``: each one's pixel, whose weight, colour, view vector and
    label (or None) are given per pixel) to ``vol``: ``_walk``'s updates, each voxel's in the same order."""
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    ids = vol.index.find(uniq)
    new = np.flatnonzero(ids < 0)
    if len(new):
        # New voxels numbered as the loop meets them: the cloud's points come out in the same order.
        met = new[np.argsort(first[new], kind="stable")]
        ids[met] = vol.n + np.arange(len(met))
        vol._reserve(vol.n + len(met))
        vol.keys[vol.n : vol.n + len(met)] = uniq[met]
        vol.n += len(met)
        vol.index.insert(uniq[new], ids[new])
    e = ids[inv]
    rows = vol.rows
    w = wt[pix]
    np.add.at(rows[:, _SDF], e, w * sdf)
    np.add.at(rows[:, _W], e, w)
    np.add.at(rows[:, _N], e, 1.0)
    surf = np.flatnonzero(np.abs(sdf) < 0.5 * vol.voxel_m)  # the pixel's surface lies in the voxel
    es, ps = e[surf], pix[surf]
    ws = w[surf]
    for k in range(3):
        np.add.at(rows[:, _RGB + k], es, ws * rgb[ps, k].astype(np.float64))
        np.add.at(rows[:, _VIEW + k], es, view[ps, k])
    np.add.at(rows[:, _CW], es, ws)
    np.add.at(rows[:, _VN], es, 1.0)
    if lab is not None:
        ls = lab[ps]
        ok = (ls >= 0) & (ls <= LABEL_MAX)
        _vote(rows, es[ok], (ls[ok] + 1).astype(np.float64), ws[ok])


def _vote(rows, e, tag, wt):
    """The weighted Boyer-Moore steps of ``_walk`` for labels ``tag`` (label + 1) of weight ``wt`` into
    voxels ``e`` (in the loops' order). A voxel whose labels this frame are one, the one it holds or its
    first, only adds their weights (in order, as the loop does); the others step rank by rank."""
    if len(e) == 0:
        return
    order = np.argsort(e, kind="stable")
    e, tag, wt = e[order], tag[order], wt[order]
    start = np.flatnonzero(np.r_[True, e[1:] != e[:-1]])
    count = np.diff(np.r_[start, len(e)])
    ev = e[start]
    cur = rows[ev, _LAB]
    one = (np.minimum.reduceat(tag, start) == np.maximum.reduceat(tag, start)) & (
        (cur == tag[start]) | (cur == 0.0))  # no label yet: its weight is 0, so it takes the first
    rows[ev[one], _LAB] = tag[start[one]]
    simple = np.repeat(one, count)
    np.add.at(rows[:, _LABW], e[simple], wt[simple])
    start, count, ev = start[~one], count[~one], ev[~one]
    for r in range(int(count.max(initial=0))):
        live = count > r
        at, v = start[live] + r, ev[live]
        cur, c, t, w = rows[v, _LAB], rows[v, _LABW], tag[at], wt[at]
        same, down = cur == t, c >= w
        rows[v, _LABW] = np.where(same, c + w, np.where(down, c - w, w - c))
        rows[v, _LAB] = np.where(same | down, cur, t)


def _extract_array(vol: TsdfVolume, min_updates, crossing_max):
    """``_extract``'s twin: (xyz, rgb, lab, view, support) of the crossings, in the same order."""
    n, voxel = vol.n, vol.voxel_m
    rows, keys = vol.rows[:n], vol.keys[:n]
    cnt = rows[:, _N]
    a = np.flatnonzero(cnt >= min_updates)
    tsd = rows[:, _SDF] / rows[:, _W]
    base = unpack_keys(keys[a]) - AXIS_HALF
    # (a, axis) pairs in the loop's order: voxel by voxel, +x, +y, +z.
    steps = np.array([1 << (2 * AXIS_BITS), 1 << AXIS_BITS, 1], np.int64)
    b = vol.index.find((keys[a][:, None] + steps[None, :]).reshape(-1)).reshape(-1, 3)
    ai = np.repeat(a, 3).reshape(-1, 3)
    ok = b >= 0
    bb = np.where(ok, b, 0)
    ta, tb = tsd[ai], tsd[bb]
    ok &= (cnt[bb] >= min_updates) & ((ta >= 0.0) != (tb >= 0.0)) & ~(np.abs(ta - tb) > crossing_max)
    a_first = np.abs(ta) <= np.abs(tb)
    near, other = np.where(a_first, ai, bb), np.where(a_first, bb, ai)
    cw = rows[:, _CW]
    src = np.where(cw[near] > 0.0, near, other)
    ok &= ~(cw[src] <= 0.0)
    pa, axis = np.nonzero(ok)
    ta, tb, b, a_, src = ta[ok], tb[ok], b[ok], a[pa], src[ok]
    f = ta / (ta - tb)
    xyz = (base[pa] + 0.5) * voxel
    xyz[np.arange(len(pa)), axis] += f * voxel
    rgb = rows[src, _RGB : _RGB + 3] / rows[src, _CW][:, None]
    near = near[ok]
    lsrc = np.where(rows[near, _LAB] > 0.0, near, other[ok])
    lab = rows[lsrc, _LAB].astype(np.int64) - 1
    vn = rows[a_, _VN] + rows[b, _VN]
    view = (rows[a_, _VIEW : _VIEW + 3] + rows[b, _VIEW : _VIEW + 3]) / vn[:, None]
    support = np.minimum(cnt[a_], cnt[b])
    return (xyz.astype(np.float32), rgb.astype(np.float32), lab.astype(np.int32), view.astype(np.float32),
            support.astype(np.float32))


class TsdfVolume:
    """A sparse TSDF volume fed one frame at a time; ``cloud`` extracts its surface.

    ``add`` takes what ``kernels.FrameFuser.add`` takes (depth, colours, labels, the float (3, 4)
    camera-to-volume transform, the unit-depth rays and the unit vectors back along them, the stride)
    and the frame's depth sigma per depth squared (``noise_rel``: sigma = noise_rel * depth^2).
    ``compiled``: the numba loops (None: when numba is installed) or the array code, the same bits."""

    def __init__(self, voxel_m: float, min_depth_m: float, max_depth_m: float, labelled: bool, *,
                 sigma_floor_m: float, trunc_min_m: float, trunc_sigmas: float, trunc_back_m: float,
                 max_sub_rays: int = 3, capacity: int = 1 << 18, compiled: bool | None = None):
        self.compiled = AVAILABLE if compiled is None else bool(compiled)
        if self.compiled and not AVAILABLE:
            raise RuntimeError("numba is not installed")
        self.voxel_m = float(voxel_m)
        self.dmin, self.dmax = float(min_depth_m), float(max_depth_m)
        self.labelled = bool(labelled)
        self.sigma_floor_m, self.trunc_min_m = float(sigma_floor_m), float(trunc_min_m)
        self.trunc_sigmas, self.trunc_back_m = float(trunc_sigmas), float(trunc_back_m)
        self.max_sub_rays = int(max_sub_rays)
        self.n = 0
        self.points = 0
        cap = kernels._pow2_at_least(capacity, 16)
        self.keys = np.empty(cap, np.int64)
        self.rows = np.zeros((cap, _ROW), np.float64)
        if self.compiled:
            self.table, self.shift = kernels._table(2 * cap)
        else:
            self.index = _SortedIndex()
        self._no_sem = np.zeros((1, 1), np.int32)

    def add(self, depth: np.ndarray, rgb: np.ndarray, sem: np.ndarray | None, m: np.ndarray, rays: np.ndarray,
            backs: np.ndarray, stride: int, noise_rel: float, max_depth_m: float | None = None) -> bool:
        """Integrate one frame (depth up to ``max_depth_m`` when given); False when a voxel lies outside
        the packable range (then stop)."""
        h, w = depth.shape
        dmax = self.dmax if max_depth_m is None else min(self.dmax, max_depth_m)
        # Neighbouring pixels' rays differ by one pixel's pitch (unit-depth rays: x / z and y / z).
        pitch = np.array([abs(rays[1, 0] - rays[0, 0]) if w > stride else 0.0,
                          abs(rays[(w + stride - 1) // stride, 1] - rays[0, 1]) if h > stride else 0.0])
        m = np.asarray(m, np.float64)
        if self.compiled:
            # Room for every voxel the bands can reach: each pixel's band, in half-voxel steps.
            pixels = ((h + stride - 1) // stride) * ((w + stride - 1) // stride)
            sigma = max(noise_rel * dmax * dmax, self.sigma_floor_m)
            band = max(self.trunc_min_m, self.trunc_sigmas * sigma) + self.trunc_back_m
            self._reserve(self.n + pixels * self.max_sub_rays**2 * (int(band / (0.5 * self.voxel_m)) + 2))
            self.n, status, used = integrate(
                depth, rgb, sem if self.labelled else self._no_sem, self.labelled, stride, rays, backs, pitch,
                m, self.dmin, dmax, self.voxel_m, float(noise_rel), self.sigma_floor_m,
                self.trunc_min_m, self.trunc_sigmas, self.trunc_back_m, self.max_sub_rays, self.table, self.shift,
                self.keys, self.rows, self.n,
            )
        else:
            status, used = _integrate_array(self, depth, rgb, sem, stride, rays, backs, pitch, m, dmax,
                                            float(noise_rel))
        self.points += used
        return status == 0

    def cloud(self, min_updates: int, crossing_max_vox: float, fill_m: float = 0.0,
              label_names: dict[int, str] | None = None) -> PointCloud:
        """The volume's surface: one point per zero crossing between neighbouring voxels updated at least
        ``min_updates`` times; with ``fill_m`` > 0 also those updated less where no such point lies within
        ``fill_m`` (a surface only a look or two reached, not the fringe of a well-seen one)."""
        floor = 1.0 if fill_m > 0 else float(min_updates)
        crossing_max = crossing_max_vox * self.voxel_m
        if self.compiled:
            n = self.n
            # Up to three crossings a voxel (float32: what the cloud keeps anyway).
            out = (np.empty((3 * n, 3), np.float32), np.empty((3 * n, 3), np.float32), np.empty(3 * n, np.int32),
                   np.empty((3 * n, 3), np.float32), np.empty(3 * n, np.float32))
            k = extract(self.keys, self.rows, n, self.table, self.shift, self.voxel_m, floor, crossing_max, *out)
            xyz, rgb, lab, view, support = (a[:k] for a in out)
        else:
            xyz, rgb, lab, view, support = _extract_array(self, floor, crossing_max)
        keep = np.arange(len(xyz))
        if fill_m > 0:
            strong = support >= min_updates
            weak = np.flatnonzero(~strong)
            if len(weak) and strong.any():
                from scipy.spatial import cKDTree

                dist, _ = cKDTree(xyz[strong]).query(xyz[weak], distance_upper_bound=fill_m, workers=2)
                strong[weak[~np.isfinite(dist)]] = True
            keep = np.flatnonzero(strong)
        return PointCloud(xyz[keep], np.clip(np.rint(rgb[keep]), 0, 255).astype(np.uint8),
                          lab[keep] if self.labelled else None, dict(label_names or {}),
                          quantise_view_dirs(view[keep]))

    def _reserve(self, need: int) -> None:
        if need > len(self.keys):
            cap = kernels._pow2_at_least(need, 2 * len(self.keys))
            self.keys = kernels._grown(self.keys, cap, self.n)
            self.rows = kernels._grown(self.rows, cap, self.n)
        if self.compiled and need > kernels._MAX_LOAD * len(self.table):
            self.table, self.shift = kernels._table(
                kernels._pow2_at_least(int(need / kernels._MAX_LOAD), 2 * len(self.table)))
            kernels.rehash(self.keys, self.n, self.table, self.shift)
