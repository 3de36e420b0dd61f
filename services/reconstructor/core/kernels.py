"""Compiled hot loops of the RGB-D fusion (numba), with results identical to the array code.

Two kernels, each the compiled twin of an array path that stays the reference (and the fallback
when numba is missing):

* :class:`FrameFuser` back-projects every valid depth pixel of a batch of frames, computes its
  voxel key and adds it to per-voxel sums in one pass per frame: position, colour, count, label
  votes and the unit vector from the point back to the camera (the pixel's viewing ray, reversed
  and rotated into the target frame; the voxel's mean of them is where it was seen from). Voxels
  live in an open-addressing hash table keyed by the packed voxel key, so nothing is sized by the
  batch's bounding box and no point array is ever built. The float32 back-projection and view
  vectors, the float32 voxel binning and the float64 sums in point order reproduce
  ``RgbdReconstructor``'s array back-projection followed by ``voxel._reduce_dense`` bit for bit
  (the tests compare them exactly).
* :func:`knn_mean_distances` gives, per point, the mean distance to its ``k`` nearest points
  (itself included, as open3d counts it) by searching growing shells of a dense cell grid, which
  beats a k-d tree several times on voxel-downsampled clouds where a point's neighbours sit a few
  cells away. The statistical outlier test on top of it is open3d's, so the kept points are the same.

The kernels release the GIL: the caller runs batches (or point ranges) on a few threads at once.
"""

from __future__ import annotations

import logging
import math

import numpy as np

log = logging.getLogger(__name__)

from shared.jit import AVAILABLE, kernel

# Packing of voxel keys, shared with voxel.py (which imports these).
AXIS_BITS = 15
AXIS_HALF = 1 << (AXIS_BITS - 1)
LABEL_BITS = 16
LABEL_MAX = (1 << LABEL_BITS) - 2  # labels 0..65534; the label field stores label + 1

_EMPTY = -1  # packed keys are non-negative
_HASH_MUL = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing: the high bits of key * 2^64/phi
_MAX_LOAD = 0.5


def _slot(key, shift):
    return np.int64((np.uint64(key) * _HASH_MUL) >> np.uint64(shift))


def _find_or_add(table, shift, key, n, out_keys):
    """Entry id of ``key`` in the (cap, 2) [key, id] table (appended as entry ``n`` when new); (id, n)."""
    mask = table.shape[0] - 1
    s = _slot(key, shift)
    while True:
        k = table[s, 0]
        if k == key:
            return table[s, 1], n
        if k == _EMPTY:
            table[s, 0] = key
            table[s, 1] = n
            out_keys[n] = key
            return n, n + 1
        s = (s + 1) & mask


def _rehash(keys, n, table, shift):
    """Insert the first ``n`` (distinct) ``keys`` with their positions as ids into an empty table."""
    mask = table.shape[0] - 1
    for i in range(n):
        key = keys[i]
        s = _slot(key, shift)
        while table[s, 0] != _EMPTY:
            s = (s + 1) & mask
        table[s, 0] = key
        table[s, 1] = i


# Columns of an entry row: position sums, colour sums, count, the voxel's first label with its
# votes, packed as (label + 1) * 2^32 + votes (exact in a float64), and the sums of the unit
# vectors towards the camera.
_ROW = 11
_VOTE = 7
_VIEW = 8
_VOTE_UNIT = 4294967296.0  # 2^32


def _fuse_frame(
    depth, rgb, sem, labelled, stride, rays, backs, m, dmin, dmax, inv_voxel,
    table, shift, keys, rows, n, vtable, vshift, vkeys, vcnt, nv, row_keys, row_ids,
):
    """Add one frame's valid pixels to the voxel table; returns (entries, votes, points, status).

    status is 0, or 1 when a point falls outside the packable range (nothing more is added then).
    ``backs`` are the pixels' unit vectors towards the camera in camera axes; ``m``'s rotation turns
    them into the target frame (the same float32 expression as the array code). The caller
    guarantees room for one new entry and one new overflow vote per pixel; ``row_keys`` and
    ``row_ids`` are scratch of at least the strided width."""
    h = depth.shape[0]
    w = depth.shape[1]
    hs = (h + stride - 1) // stride
    ws = (w + stride - 1) // stride
    m00, m01, m02, m03 = m[0, 0], m[0, 1], m[0, 2], m[0, 3]
    m10, m11, m12, m13 = m[1, 0], m[1, 1], m[1, 2], m[1, 3]
    m20, m21, m22, m23 = m[2, 0], m[2, 1], m[2, 2], m[2, 3]
    half = np.int64(AXIS_HALF)
    for j in range(ws):
        row_keys[j] = _EMPTY
    points = 0
    for i in range(hs):
        r = i * stride
        last_key = np.int64(_EMPTY)
        last_id = np.int64(0)
        for j in range(ws):
            c = j * stride
            d = depth[r, c]
            if not (d > dmin and d < dmax):  # NaN compares False, as in the array code
                continue
            q = i * ws + j
            xc = rays[q, 0] * d
            yc = rays[q, 1] * d
            # Same float32 expressions, same association, as the array back-projection.
            px = m00 * xc + m01 * yc + m02 * d + m03
            py = m10 * xc + m11 * yc + m12 * d + m13
            pz = m20 * xc + m21 * yc + m22 * d + m23
            cx = np.int64(np.floor(px * inv_voxel))
            cy = np.int64(np.floor(py * inv_voxel))
            cz = np.int64(np.floor(pz * inv_voxel))
            if (cx < -half) | (cx >= half) | (cy < -half) | (cy >= half) | (cz < -half) | (cz >= half):
                return n, nv, points, 1
            key = ((cx + half) << (2 * AXIS_BITS)) | ((cy + half) << AXIS_BITS) | (cz + half)
            # Neighbouring pixels (left, above) mostly share a voxel: skip the hash probe then.
            if key != last_key:
                if key == row_keys[j]:
                    last_id = row_ids[j]
                else:
                    last_id, n = _find_or_add(table, shift, key, n, keys)
                last_key = key
            row_keys[j] = key
            row_ids[j] = last_id
            e = last_id
            rows[e, 0] += np.float64(px)
            rows[e, 1] += np.float64(py)
            rows[e, 2] += np.float64(pz)
            rows[e, 3] += np.float64(rgb[r, c, 0])
            rows[e, 4] += np.float64(rgb[r, c, 1])
            rows[e, 5] += np.float64(rgb[r, c, 2])
            rows[e, 6] += 1.0
            bx = backs[q, 0]
            by = backs[q, 1]
            bz = backs[q, 2]
            rows[e, _VIEW] += np.float64(m00 * bx + m01 * by + m02 * bz)
            rows[e, _VIEW + 1] += np.float64(m10 * bx + m11 * by + m12 * bz)
            rows[e, _VIEW + 2] += np.float64(m20 * bx + m21 * by + m22 * bz)
            points += 1
            if labelled:
                lab = np.int64(sem[r, c])
                if lab >= 0 and lab <= LABEL_MAX:
                    slot = rows[e, _VOTE]
                    tag = np.float64(lab + 1) * _VOTE_UNIT
                    if slot == 0.0:
                        rows[e, _VOTE] = tag + 1.0
                    elif slot - tag >= 0.0 and slot - tag < _VOTE_UNIT:
                        rows[e, _VOTE] = slot + 1.0
                    else:  # a second label in this voxel: counted in the overflow table
                        vkey = (key << LABEL_BITS) | (lab + 1)
                        v, nv = _find_or_add(vtable, vshift, vkey, nv, vkeys)
                        vcnt[v] += 1
    return n, nv, points, 0


def _knn_mean(xyz, frac, cells, dims, order, sorted_flat, head, k, cell_m, start, end, out):
    """Mean distance of points ``start:end`` to their ``k`` nearest (self included) into ``out``.

    Shell ``R`` holds the cells at Chebyshev distance ``R`` from the point's cell. After shells
    0..R every unseen point is at least ``cell_m * min_axis(min(frac + R, R + 1 - frac))`` away, so
    the search stops as soon as the k-th best distance is within that bound: exact k nearest."""
    best = np.empty(k, np.float64)
    dx_, dy_, dz_ = dims[0], dims[1], dims[2]
    npts = xyz.shape[0]
    for p in range(start, end):
        x, y, z = xyz[p, 0], xyz[p, 1], xyz[p, 2]
        cx, cy, cz = cells[p, 0], cells[p, 1], cells[p, 2]
        nf = 0
        r = 0
        while True:
            for ix in range(max(cx - r, 0), min(cx + r, dx_ - 1) + 1):
                edge_x = ix == cx - r or ix == cx + r
                for iy in range(max(cy - r, 0), min(cy + r, dy_ - 1) + 1):
                    edge = edge_x or iy == cy - r or iy == cy + r
                    # Inside the shell's x/y faces only the two z caps are new.
                    step = 1 if edge else 2 * r
                    iz = cz - r
                    while iz <= cz + r:
                        if 0 <= iz < dz_:
                            cell = (ix * dy_ + iy) * dz_ + iz
                            t = head[cell]
                            if t >= 0:
                                while t < npts and sorted_flat[t] == cell:
                                    qi = order[t]
                                    ddx = xyz[qi, 0] - x
                                    ddy = xyz[qi, 1] - y
                                    ddz = xyz[qi, 2] - z
                                    d2 = ddx * ddx + ddy * ddy + ddz * ddz
                                    if nf < k or d2 < best[nf - 1]:
                                        if nf < k:
                                            nf += 1
                                        s = nf - 1
                                        while s > 0 and best[s - 1] > d2:
                                            best[s] = best[s - 1]
                                            s -= 1
                                        best[s] = d2
                                    t += 1
                        if step == 0:
                            break
                        iz += step
            covered = cx - r <= 0 and cy - r <= 0 and cz - r <= 0 and cx + r >= dx_ - 1 and cy + r >= dy_ - 1 and cz + r >= dz_ - 1
            if covered:
                break
            if nf == k:
                g = min(
                    min(frac[p, 0] + r, r + 1 - frac[p, 0]),
                    min(frac[p, 1] + r, r + 1 - frac[p, 1]),
                    min(frac[p, 2] + r, r + 1 - frac[p, 2]),
                )
                bound = g * cell_m * (1.0 - 1e-9)
                if best[k - 1] <= bound * bound:
                    break
            r += 1
        acc = 0.0
        for s in range(nf):
            acc += math.sqrt(best[s])
        out[p] = acc / nf if nf > 0 else 0.0


if AVAILABLE:
    _jit = kernel(error_model="numpy")
    _slot = _jit(_slot)
    _find_or_add = _jit(_find_or_add)
    rehash = _jit(_rehash)
    fuse_frame = _jit(_fuse_frame)
    knn_mean = _jit(_knn_mean)
else:  # pragma: no cover
    rehash = fuse_frame = knn_mean = None


class FrameFuser:
    """Per-voxel sums of a batch of frames, fed one frame at a time (compiled; needs numba).

    ``add`` takes a depth image (float32, 0 or NaN = no measurement), its colours, optional
    semantic labels, the float32 (3, 4) transform from camera to the target frame, the float32
    (H' * W', 3) unit-depth rays of the (strided) pixel grid and the float32 (H' * W', 3) unit
    vectors back along them (towards the camera, camera axes); ``result`` gives what
    ``voxel._reduce_dense`` gives for the same points: sorted keys, sums, counts, view-vector sums
    and label votes.
    """

    def __init__(self, voxel_m: float, min_depth_m: float, max_depth_m: float, labelled: bool,
                 capacity: int = 1 << 16):
        if not AVAILABLE:
            raise RuntimeError("numba is not installed")
        self.inv_voxel = np.float32(1.0 / voxel_m)
        self.dmin = np.float32(min_depth_m)
        self.dmax = np.float32(max_depth_m)
        self.labelled = bool(labelled)
        self.n = 0
        self.nv = 0
        self.points = 0
        cap = _pow2_at_least(capacity, 16)
        self.keys = np.empty(cap, np.int64)
        self.rows = np.zeros((cap, _ROW), np.float64)
        self.table, self.shift = _table(2 * cap)
        self.vkeys = np.empty(16, np.int64)
        self.vcnt = np.zeros(16, np.int64)
        self.vtable, self.vshift = _table(32)
        self._no_sem = np.zeros((1, 1), np.int32)
        self._row_keys = np.empty(0, np.int64)
        self._row_ids = np.empty(0, np.int64)

    def add(self, depth: np.ndarray, rgb: np.ndarray, sem: np.ndarray | None, m: np.ndarray,
            rays: np.ndarray, backs: np.ndarray, stride: int, max_depth_m: float | None = None) -> bool:
        """Fuse one frame (depth up to ``max_depth_m`` when given, nearer than the fuser's own);
        False when a point lies outside the packable range (then stop)."""
        h, w = depth.shape
        ws = (w + stride - 1) // stride
        room = ((h + stride - 1) // stride) * ws
        self._reserve(self.n + room, self.nv + room if self.labelled else 0)
        if len(self._row_keys) < ws:
            self._row_keys = np.empty(ws, np.int64)
            self._row_ids = np.empty(ws, np.int64)
        sem = sem if self.labelled else self._no_sem
        self.n, self.nv, pts, status = fuse_frame(
            depth, rgb, sem, self.labelled, stride, rays, backs, m, self.dmin,
            self.dmax if max_depth_m is None else np.float32(min(self.dmax, max_depth_m)), self.inv_voxel,
            self.table, self.shift, self.keys, self.rows, self.n,
            self.vtable, self.vshift, self.vkeys, self.vcnt, self.nv, self._row_keys, self._row_ids,
        )
        self.points += pts
        return status == 0

    def result(self):
        """``((keys, sxyz, srgb, cnt, sview), (vote_keys, vote_counts) or None)``, keys ascending,
        float64 sums."""
        n, nv = self.n, self.nv
        keys = self.keys[:n]
        order = np.argsort(keys)
        rows = self.rows[:n][order]
        part = (keys[order], rows[:, 0:3], rows[:, 3:6], rows[:, 6].copy(), rows[:, _VIEW:_VIEW + 3])
        votes = None
        if self.labelled:
            slot = self.rows[:n, _VOTE]
            has = slot > 0
            lab1 = np.floor(slot[has] / _VOTE_UNIT)
            pk = np.concatenate([(keys[has] << LABEL_BITS) | lab1.astype(np.int64), self.vkeys[:nv]])
            cnt = np.concatenate([slot[has] - lab1 * _VOTE_UNIT, self.vcnt[:nv].astype(np.float64)])
            vo = np.argsort(pk)
            votes = (pk[vo], cnt[vo])
        return part, votes

    def _reserve(self, n_need: int, nv_need: int) -> None:
        if n_need > len(self.keys):
            cap = _pow2_at_least(n_need, 2 * len(self.keys))
            self.keys = _grown(self.keys, cap, self.n)
            self.rows = _grown(self.rows, cap, self.n)
        if n_need > _MAX_LOAD * len(self.table):
            self.table, self.shift = _table(_pow2_at_least(int(n_need / _MAX_LOAD), 2 * len(self.table)))
            rehash(self.keys, self.n, self.table, self.shift)
        if nv_need > len(self.vkeys):
            cap = _pow2_at_least(nv_need, 2 * len(self.vkeys))
            self.vkeys = _grown(self.vkeys, cap, self.nv)
            self.vcnt = _grown(self.vcnt, cap, self.nv)
        if nv_need > _MAX_LOAD * len(self.vtable):
            self.vtable, self.vshift = _table(_pow2_at_least(int(nv_need / _MAX_LOAD), 2 * len(self.vtable)))
            rehash(self.vkeys, self.nv, self.vtable, self.vshift)


def _pow2_at_least(n: int, floor: int) -> int:
    return max(floor, 1 << max(0, int(n - 1).bit_length()))


def _table(cap: int):
    cap = _pow2_at_least(cap, 16)
    return np.full((cap, 2), _EMPTY, np.int64), np.int64(64 - (cap.bit_length() - 1))


def _grown(a: np.ndarray, cap: int, used: int) -> np.ndarray:
    out = np.zeros((cap, *a.shape[1:]), a.dtype)
    out[:used] = a[:used]
    return out


def knn_mean_distances(xyz: np.ndarray, k: int, cell_m: float, threads: int = 1,
                       max_cells: int = 48_000_000, cells_per_point: int = 8) -> np.ndarray:
    """(N,) mean distance of each point to its ``k`` nearest points, itself included (compiled).

    ``cell_m`` should be about the point spacing (the voxel size of a downsampled cloud); it is
    enlarged when the bounding box would need more than ``max_cells`` cells, or more than
    ``cells_per_point`` cells per point. Exact whatever it is.
    """
    if not AVAILABLE:
        raise RuntimeError("numba is not installed")
    xyz = np.ascontiguousarray(xyz, np.float64)
    n = len(xyz)
    out = np.zeros(n, np.float64)
    if n == 0 or k < 1:
        return out
    lo = xyz.min(axis=0)
    ext = xyz.max(axis=0) - lo
    cell_m = float(cell_m)
    # Past a few cells per point most cells are empty: a sparse part of the cloud (scattered outliers, a
    # region's far points, which stretch the bounding box) then searches shell after shell of empty
    # cells, and ``head`` alone is 8 bytes a cell (a 9-frame test region: 8975 points, 28.6e6 cells,
    # 2.1 s of CPU; 8 cells per point: 0.02 s). The k nearest are exact at any cell size, and each
    # mean adds the same sorted distances, so the cap changes the time, never a bit of the result
    # (a 3 cm room of 131e3 points with 300 outliers: 3.4 s -> 0.3 s; without them 0.23 -> 0.14 s).
    limit = max(1, min(int(max_cells), int(cells_per_point) * n))
    while True:
        dims = (np.floor(ext / cell_m).astype(np.int64) + 1)
        if int(dims.prod()) <= limit:
            break
        cell_m *= 1.5
    u = (xyz - lo) / cell_m
    cells = np.minimum(np.floor(u).astype(np.int64), dims - 1)
    frac = np.clip(u - cells, 0.0, 1.0)
    flat = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(flat, kind="stable")
    sorted_flat = flat[order]
    head = np.full(int(dims.prod()), -1, np.int64)
    first = np.flatnonzero(np.r_[True, sorted_flat[1:] != sorted_flat[:-1]])
    head[sorted_flat[first]] = first
    args = (xyz, frac, cells, dims, order, sorted_flat, head, int(k), cell_m)
    threads = max(1, min(int(threads), n // 4096 + 1))
    if threads == 1:
        knn_mean(*args, 0, n, out)
        return out
    from concurrent.futures import ThreadPoolExecutor

    # Interleaved chunks balance dense and sparse parts of the cloud between the threads.
    bounds = np.linspace(0, n, 8 * threads + 1).astype(np.int64)
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(lambda i: knn_mean(*args, int(bounds[i]), int(bounds[i + 1]), out), range(len(bounds) - 1)))
    return out


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernels; returns the seconds it took."""
    if not AVAILABLE:
        return 0.0
    import time

    t0 = time.perf_counter()
    f = FrameFuser(0.1, 0.1, 8.0, True, 16)
    rays = np.ones((4, 3), np.float32)
    f.add(np.ones((2, 2), np.float32), np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.int32),
          np.eye(4, dtype=np.float32)[:3], rays, -rays, 1)
    f.result()
    knn_mean_distances(np.random.default_rng(0).uniform(0, 1, (64, 3)), 4, 0.2)
    dt = time.perf_counter() - t0
    log.debug("reconstructor kernels ready in %.2f s", dt)
    return dt
