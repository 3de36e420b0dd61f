"""The numpy array backend of the splatting renderer (``_NumpyOps``: the small set of array
operations both algorithms are written against, with the compiled front pass of :mod:`kernels`),
and the per-map arrays every backend caches on an :class:`IndexedCloud` (spacing, normals, sides).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from libs.pointrender import kernels, visibility
from libs.pointrender.cloud import IndexedCloud


# --- array backends ------------------------------------------------------------------------------


@dataclass
class _CloudArrays:
    """Per-map, per-backend arrays (built once, cached on the IndexedCloud)."""

    x: object
    y: object
    z: object
    rgb: object  # float32 (N, 3)
    labels: object | None
    rgb_packed: object | None = None  # numpy only: r + g 2^17 + b 2^34 as float64
    rgb_u32: object | None = None  # numpy only: r | g << 8 | b << 16 as int32, for the kernels


def point_tree_of(index: IndexedCloud):
    """The k-d tree of the index's points (:func:`visibility.point_tree`), cached on the index: the
    spacing, the normals and the sides' vote each query it, and a 1.6 M-point map's tree is ~0.9 s."""
    key = ("point-tree",)
    if key not in index.cache:
        index.cache[key] = visibility.point_tree(index.cloud.xyz)
    return index.cache[key]


def point_spacing_of(index: IndexedCloud, neighbours: int) -> np.ndarray:
    """Per-point local spacing (float32 m, in the index's point order), cached on the index."""
    key = ("point-spacing", neighbours)
    if key not in index.cache:
        index.cache[key] = visibility.point_spacing(index.cloud.xyz, neighbours, tree=point_tree_of(index))
    return index.cache[key]


def point_normals_of(index: IndexedCloud, neighbours: int, spacing_neighbours: int | None = None) -> np.ndarray:
    """Per-point unoriented unit normal (float32 (N, 3), in the index's point order), cached on the
    index; with ``spacing_neighbours`` the spacing of :func:`point_spacing_of` comes from the same
    neighbour query when it is not cached yet."""
    key = ("point-normals", neighbours)
    if key not in index.cache:
        sp_key = ("point-spacing", spacing_neighbours)
        if spacing_neighbours is not None and sp_key not in index.cache:
            index.cache[sp_key], index.cache[key] = visibility.point_spacing_and_normals(
                index.cloud.xyz, spacing_neighbours, neighbours, tree=point_tree_of(index))
        else:
            index.cache[key] = visibility.point_normals(index.cloud.xyz, neighbours, tree=point_tree_of(index))
    return index.cache[key]


# The cached arrays that follow from the points' positions alone (not their colours, labels or view
# directions): another index of the same points in the same order may take them as they are.
_GEOMETRY_KEYS = frozenset({"point-tree", "point-spacing", "point-normals"})


def share_point_geometry(source: IndexedCloud, target: IndexedCloud) -> int:
    """Give ``target`` the spacing and normals already cached on ``source`` (those it lacks), when
    both index the same points in the same order (the same positions, block size and shuffle seed,
    e.g. the same map with view directions added): a neighbour query and eigen-solve per point is
    then paid once for both. Returns how many arrays were shared; ValueError for other points."""
    if not (np.array_equal(source.cloud.xyz, target.cloud.xyz) and np.array_equal(source.starts, target.starts)):
        raise ValueError("share_point_geometry: the two indexes do not hold the same points in the same order")
    shared = {k: v for k, v in source.cache.items()
              if isinstance(k, tuple) and k and k[0] in _GEOMETRY_KEYS and k not in target.cache}
    target.cache.update(shared)
    return len(shared)


def point_sides_of(index: IndexedCloud, neighbours: int, spacing_neighbours: int | None,
                   min_agreement: float, vote_neighbours: int = 0,
                   min_vote: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(normals float32 (N, 3), sided uint8 (N,)) of the index's points, cached: the normals of
    :func:`point_normals_of`, turned towards the side each point was seen from where the map
    records it (:func:`visibility.orient_normals`); ``sided`` 0 where that side is not known.
    ``vote_neighbours`` > 1: each point's side is then its neighbourhood's vote
    (:func:`visibility.vote_sides`, ``min_vote``)."""
    key = ("point-sides", neighbours, min_agreement, vote_neighbours, min_vote if vote_neighbours > 1 else None)
    if key not in index.cache:
        normals = point_normals_of(index, neighbours, spacing_neighbours)
        sides = visibility.orient_normals(normals, index.cloud.view_dirs, min_agreement)
        if vote_neighbours > 1:
            sides = visibility.vote_sides(index.cloud.xyz, *sides, vote_neighbours, min_vote,
                                          tree=point_tree_of(index))
        index.cache[key] = sides
    return index.cache[key]


def _index_grid(h: int, w: int, axis: int) -> np.ndarray:
    """(h, w) int32 row (axis 0) or column (axis 1) index of every pixel."""
    line = np.arange(h if axis == 0 else w, dtype=np.int32)
    return np.broadcast_to(line[:, None] if axis == 0 else line[None, :], (h, w))


_PACK = float(2**17)
_PACK_MAX_COUNT = 514  # 514 * 255 < 2^17: packed per-pixel sums stay exact up to this many points


def _add_in_order(n: int, idx: np.ndarray, vals: np.ndarray) -> np.ndarray:
    """float32 (n,): ``vals`` summed per index in float32, one by one in array order (``np.add.at``
    is unbuffered and ordered): the sums the compiled front pass keeps, to the bit."""
    out = np.zeros(n, np.float32)
    np.add.at(out, idx, np.asarray(vals, np.float32))
    return out


class _NumpyOps:
    name = "numpy"
    concurrent_views = True

    def asarray(self, a: np.ndarray):
        return a

    def to_numpy(self, a) -> np.ndarray:
        return a

    def full(self, n: int, value: float):
        return np.full(n, value, dtype=np.float32)

    def scatter_min(self, n: int, idx, vals):
        out = np.full(n, np.inf, dtype=np.float32)
        np.minimum.at(out, idx, vals)
        return out

    def scatter_max_int(self, n: int, idx, vals):
        out = np.full(n, -1, dtype=np.int64)
        np.maximum.at(out, idx, vals)
        return out

    def scatter_add(self, n: int, idx, cols: Sequence):
        return [np.bincount(idx, weights=c, minlength=n).astype(np.float32) for c in cols]

    def sum_in_order(self, n: int, idx, vals):
        return _add_in_order(n, idx, vals)

    def accumulate_front(self, n: int, q, front, z, arrays: _CloudArrays, idx, qu, qv, spacing=None,
                         unseen=None, unseen_rgb=(0, 0, 0)):
        """Per-pixel sums of the front layer; points of ``unseen`` (bool, per point of ``idx``) add
        the colour ``unseen_rgb`` instead of their own (:func:`_unseen_side`)."""
        sel = np.flatnonzero(front)
        lq = q[sel]
        s_sp = None if spacing is None else _add_in_order(n, lq, spacing[sel])
        cnt = np.bincount(lq, minlength=n)
        s_z = _add_in_order(n, lq, z[sel])
        if cnt[: n - 1].max(initial=0) <= _PACK_MAX_COUNT:
            # Colour and offset sums are sums of small integers: packing three (two) of them into
            # one float64 keeps them exact and saves four of the six weighted bincounts.
            packed = arrays.rgb_packed[idx[sel]]
            if unseen is not None:
                r, g, b = (float(v) for v in unseen_rgb)
                packed = np.where(unseen[sel], r + g * _PACK + b * _PACK**2, packed)
            rgb = np.bincount(lq, weights=packed, minlength=n)
            uv = np.bincount(lq, weights=qu[sel] + qv[sel] * _PACK, minlength=n)
            b = np.floor(rgb / _PACK**2)
            rgb = rgb - b * _PACK**2
            g = np.floor(rgb / _PACK)
            s_rgb = [rgb - g * _PACK, g, b]
            s_v = np.floor(uv / _PACK)
            s_u = uv - s_v * _PACK
        else:
            c = arrays.rgb[idx[sel]]
            if unseen is not None:
                c = np.where(unseen[sel, None], np.asarray(unseen_rgb, np.float32), c)
            s_rgb = [np.bincount(lq, weights=c[:, k], minlength=n) for k in range(3)]
            s_u = np.bincount(lq, weights=qu[sel], minlength=n)
            s_v = np.bincount(lq, weights=qv[sel], minlength=n)
        f32 = np.float32
        return (cnt.astype(f32), s_z.astype(f32), [a.astype(f32) for a in s_rgb], s_u.astype(f32),
                s_v.astype(f32), s_sp)

    def floor_int(self, x):
        with np.errstate(invalid="ignore"):  # points behind the camera give inf/nan; masked later
            return np.floor(x).astype(np.int64)

    def rint(self, x):
        return np.rint(x)

    def exp(self, x):
        return np.exp(x)

    def minimum(self, a, b):
        return np.minimum(a, b)

    def where(self, c, a, b):
        return np.where(c, a, b)

    def cat(self, parts):
        return np.concatenate(parts)

    def stack(self, parts):
        return np.stack(parts)

    def clamp(self, x, lo, hi):
        return np.clip(x, lo, hi)

    def to_int64(self, x):
        return x.astype(np.int64)

    # image operators of the visibility pass (2-D float32 / bool / int64 images)

    def as_f32(self, mask):
        return mask.astype(np.float32)

    def floor(self, x):
        return np.floor(x)

    def sqrt(self, x):
        return np.sqrt(x)

    def abs(self, x):
        return np.abs(x)

    def maximum(self, a, b):
        return np.maximum(a, b)

    def max_value(self, x) -> float:
        return float(x.max())

    def any(self, x) -> bool:
        return bool(x.any())

    def full2(self, h: int, w: int, value: float):
        return np.full((h, w), value, np.float32)

    def pad2(self, a, top: int, bottom: int, left: int, right: int, value):
        if not (top or bottom or left or right):
            return a
        return np.pad(a, ((top, bottom), (left, right)), constant_values=value)

    def pad_ring(self, a, value):
        return np.pad(a, 1, constant_values=value)

    def ceil(self, x):
        return np.ceil(x)

    def erode(self, x, r: int):
        # OpenCV's square min filter is exact and O(1) per pixel for any size; outside the image
        # it reads +inf, as the torch version does.
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        return cv2.erode(x, k, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)

    def erode_quadrant(self, x, m: int, sy: int, sx: int):
        """Min over the (m + 1) x (m + 1) window on side (sy, sx) of each pixel (its own row and
        column included); +inf outside the image."""
        k = np.ones((m + 1, m + 1), np.uint8)
        # cv2 reads src(x + i - anchor): anchor m takes the window above / left of the pixel.
        anchor = (m if sx < 0 else 0, m if sy < 0 else 0)
        return cv2.erode(x, k, anchor=anchor, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)

    def index_grid(self, h: int, w: int, axis: int):
        return _index_grid(h, w, axis)

    def nonzero2(self, mask):
        return np.nonzero(mask)

    def lookup(self, table: np.ndarray, index):
        return table[index.astype(np.int64)]

    def unique_values(self, x) -> list[float]:
        return np.unique(x).tolist()

    def children(self, a):
        """(H, W) -> (4, H/2, W/2): the 2x2 children of each cell, in (0,0), (0,1), (1,0), (1,1) order."""
        h, w = a.shape
        return a.reshape(h // 2, 2, w // 2, 2).transpose(1, 3, 0, 2).reshape(4, h // 2, w // 2)


    def cloud_arrays(self, index: IndexedCloud, cloud=None, tag=()) -> _CloudArrays:
        key = ("numpy-arrays", *tag)
        if key not in index.cache:
            c = index.cloud if cloud is None else cloud
            rgb = c.rgb.astype(np.float64)
            index.cache[key] = _CloudArrays(
                np.ascontiguousarray(c.xyz[:, 0]),
                np.ascontiguousarray(c.xyz[:, 1]),
                np.ascontiguousarray(c.xyz[:, 2]),
                c.rgb.astype(np.float32),
                c.labels,
                rgb[:, 0] + rgb[:, 1] * _PACK + rgb[:, 2] * _PACK**2,
                kernels.pack_rgb(c.rgb),
            )
        return index.cache[key]
