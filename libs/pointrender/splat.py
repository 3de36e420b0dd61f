"""Anticipated views of a coloured point cloud (paper Section 4.3), in two modes.

``visibility`` (the default) gives each point a footprint from its local spacing and its depth,
removes the background that shows through the gaps between foreground footprints (visibility
splatting) and fills what is left by a depth-aware pull-push (:mod:`visibility` names the
published techniques). Its front pass is the one described below (a pixel's front layer reduced
to one surfel, plus the sum of its points' spacing); the image-space passes follow it. It agrees
with the torch backend within the tolerance stated in tests/unit/renderer/test_renderer_visibility.py
(<= 0.2 % of the pixels differ; the compiled and array numpy paths are bit-identical). Its
image-space passes run compiled too (:mod:`visibility_kernels`), bit-identical to the array code.

Where the map records the side each point was seen from (``PointCloud.view_dirs``, the mean
direction towards the cameras that saw it), normals are oriented towards that side (as a range
scan's normals are towards its scanner) and a point seen from its other side is drawn in a neutral
"unknown" grey, at its depth and with its label: the face of a wall the robot never mapped shows as
a wall of unknown colour, not in the paint of the room behind it (``SplatConfig.unseen_side``).

What a view draws is bounded by its pixels, not by the map: blocks outside the frustum are
culled, and each remaining block is drawn from precomputed voxel-averaged levels of detail
(:mod:`lod`: Potree-style layered LOD, per-block selection as in sequential point trees) at the
coarsest level whose cell projects to at most ``lod_cell_px`` pixels. A far room thus costs about
its pixels, whatever its density, and per-view cost stays flat as a building grows.

``paper`` is the paper's fixed 3x3 Gaussian splat, kept for the ablation:

Every point is projected with the pinhole model; its colour and depth are spread over the 3x3
pixels around it with Gaussian weights of the distance between the point's sub-pixel position and
each pixel centre; at a pixel only the points within a depth tolerance ``epsilon`` of the minimum
depth recorded there contribute, and they are averaged with those distance weights. The label
image takes the label of the nearest splat that reaches a pixel (no blending).

Two algorithms produce this image:

* ``exact``: every point is splatted into its nine pixels and tested against the per-pixel minimum
  depth (9 contributions per point). The reference.
* ``layered`` (default): the front layer of each pixel (points within ``epsilon`` of the pixel's own
  nearest point) is first reduced to one surfel (count, sum of colour and depth, mean sub-pixel
  offset); the nine-pixel splat and the occlusion test then run on these surfels in image space.
  Per point this costs one scatter-min and one scatter-add instead of nine of each, which is what
  makes a view cost a small multiple of one pass over the visible points. It differs from
  ``exact`` only where a pixel's front layer straddles a neighbour's tolerance band (silhouettes);
  the tests bound that difference.

The minimum depth at a pixel after splatting is the 3x3 minimum filter of the per-pixel minimum
before splatting (a splat carries its point's depth unchanged), so neither algorithm needs a
nine-fold z-buffer.

Both algorithms are written once against a tiny array backend, implemented with numpy and with
torch (CUDA when available, else CPU); the two give the same images within float tolerance. The
numpy backend runs ``layered`` through compiled loops (:mod:`kernels`, numba) when numba is
installed, bit-identical to its array code and ~5x faster, and renders the views of one call on
``workers`` threads.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import weakref
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field

from shared.geometry import DEFAULT_CAMERA_HEIGHT_M, PinholeCamera, camera_pose
from libs.pointrender import kernels, occlusion, visibility, visibility_kernels
from libs.pointrender.cloud import Frustum, IndexedCloud
from libs.pointrender.errors import BackendUnavailableError
from libs.pointrender.lod import VoxelLod, build_voxel_lod, first_cell_m
from shared.registry import BackendConfig, Registry
from shared.schemas import CameraIntrinsics, ViewPose

log = logging.getLogger(__name__)

_OFFSETS = [(oy, ox) for oy in (-1, 0, 1) for ox in (-1, 0, 1)]


# Voxel level of detail per mode when SplatConfig.lod_cell_px is None: the largest cell (px) a
# block may be drawn at (see there).
LOD_CELL_PX = {"visibility": 2.5, "paper": 1.0}


_Channel8 = Annotated[int, Field(ge=0, le=255)]


class SplatConfig(BackendConfig):
    """Parameters of the splatting renderer shared by every backend."""

    # "visibility" (default): per-point footprints from local spacing and depth, a visibility pass
    # and pull-push hole filling (:mod:`visibility`). "paper": the paper's fixed 3x3 Gaussian
    # splat (section 4.3), kept for the ablation.
    mode: Literal["visibility", "paper"] = "visibility"
    # paper mode: how the 3x3 splat is computed (see the module docstring).
    algorithm: Literal["layered", "exact"] = "layered"
    kernel_sigma_px: float = Field(0.8, gt=0.05, le=5.0)
    # visibility mode: footprint radius = footprint_scale * focal * spacing / depth pixels, capped.
    # Two spacings: the visibility test needs a footprint in each quadrant of a gap pixel, and
    # the nearest point within one quadrant is farther than the nearest point overall.
    footprint_scale: float = Field(2.0, gt=0.0, le=4.0)
    max_radius_px: int = Field(24, ge=0, le=64)
    # At least the 3x3 of the paper: a randomly sampled surface leaves single empty pixels even
    # where it is dense, and the room behind must not show through them.
    min_radius_px: int = Field(1, ge=0, le=8)
    # Pull-push levels: covered pixels may take an ancestor up to 2^fill_levels px wide; gaps that
    # no footprint covers only up to 2^gap_levels px, and only inside one surface.
    # 6: a near surface the map samples sparsely (a door frame 0.2 m away, its points ~20 px
    # apart) encloses pixels no 32 px cell of its own surfels reaches.
    fill_levels: int = Field(6, ge=0, le=6)
    gap_levels: int = Field(5, ge=0, le=6)
    # ... and only where such a cell spans at most this much of the surface: a crack in a near
    # wall is filled, an unmapped stretch of a far room is left a hole.
    gap_max_m: float = Field(0.08, gt=0.0, le=1.0)
    # visibility mode: points are also projected into a band this many pixels wide around the
    # image, whose surfels are drawn nowhere but count in the visibility test's footprints. A
    # pixel near the border then sees the surface that continues past the edge: without the band
    # its quadrant towards the edge held only the few columns inside the image, and on a near
    # wall sampled at ~6 px those often held nothing but the room behind, which the test then
    # kept (most of the leak below 1 m on agent-built maps: bench.anticipation). A band as wide
    # as max_radius_px makes the border test the interior's; 16 px catches nearly all of it (a
    # footprint wider than 16 px belongs to a surface nearer than ~0.4 m) for +27 % pixels in the
    # covers' min filters. (8 px: 2 % faster per view, but below 1 m leak 0.5 -> 0.7 % and SSIM
    # 0.923 -> 0.918 at free poses, bench.anticipation --full; other bands equal.)
    guard_px: int = Field(16, ge=0, le=64)
    # Local spacing of a point: mean distance to this many nearest neighbours (once per map).
    spacing_neighbours: int = Field(4, ge=1, le=32)
    # visibility mode: hole filling accepts a fill value this much farther or nearer than the
    # enclosing surface per pixel of the cell it comes from, as a surface seen this obliquely
    # (angle between the view ray and its normal) changes depth: tan(angle) / focal per pixel.
    fill_slope_deg: float = Field(60.0, ge=0.0, le=85.0)
    # visibility mode: the colour reconstruction filter (:func:`visibility.colour_filter`) blends
    # a pixel with its 3x3 neighbours whose depth is within this fraction of its own (0: off).
    colour_filter_rel: float = Field(0.05, ge=0.0, le=0.5)
    # visibility mode: depth tolerance of the visibility test (and of the hole filling's "same
    # surface"): a surfel is background seen through a gap when it lies more than
    #   visibility_tolerance_m + visibility_tolerance_rel * depth + visibility_slope_px * slope
    # behind the surface that encloses it, where slope is its own surface's depth change per pixel
    # (from the map's normals, capped at visibility_max_incidence_deg between ray and normal).
    # This is the slope-scaled depth bias of z-buffered rendering (OpenGL's polygon offset
    # factor): a surface seen face-on gets ~2-4 cm, below half the thinnest wall (10 cm between
    # rooms in our houses), so a wall's far face no longer blends into its near face's pixels; a
    # surface seen at a grazing angle gets the depth it spans over a few pixels, so it does not
    # occlude itself. (The flat tolerance it replaces, 4 cm + 3 %, exceeded 10 cm beyond 2 m.)
    # visibility_slope_px 0: no normals, the flat tolerance alone.
    visibility_tolerance_m: float = Field(0.02, ge=0.0)
    visibility_tolerance_rel: float = Field(0.005, ge=0.0)
    visibility_slope_px: float = Field(1.0, ge=0.0, le=16.0)
    visibility_max_incidence_deg: float = Field(80.0, gt=0.0, lt=90.0)
    # Normal of a point: least-variance axis of it and this many nearest neighbours (once per map).
    normal_neighbours: int = Field(10, ge=3, le=64)
    # visibility mode, maps that record where each point was seen from (PointCloud.view_dirs): a
    # point seen from one side of its surface only is drawn in unseen_side_rgb, a neutral grey
    # (the "unknown" of occupancy maps; its depth and label stay, it still occludes) where a view
    # looks at its other side, by more than unseen_side_cos between its normal and the ray to the
    # camera. A wall between two rooms whose near face the robot never mapped then shows as a wall
    # of unknown colour, not in the neighbouring room's paint 10 cm behind. Grey, not black: black
    # is a hole (no surface), and a wall drawn black reads as an opening. A point's side is known
    # where its normal and its mean view direction agree by at least side_min_agreement (a thin
    # object seen from both sides has none). bench.anticipation, 48 free poses, bands < 1 / 1-2 /
    # > 2 m: on generated:0's rgbd map surfaces 5 cm behind the true one drawn in their own colour
    # over all pixels 15.1 / 8.2 / 13.0 % without the test, 1.3 / 3.1 / 2.7 % with it, all-pixel
    # SSIM equal (0.90 / 0.87 / 0.85; 0.77 / 0.82 / 0.77 had the grey been black). The margins
    # are for normals' errors: at 0.15 and 0.2 the rgbd map kept 0.7 / 2.3 / 1.7 %, but on the
    # depth-noise map (normals of noisy points) 1.2-2.6 % of the mapped pixels turned grey (SSIM
    # -0.02 to -0.04, a candidate band below 0.85); at 0.3 and 0.5, 0.3-1.0 % (SSIM -0.004 to
    # -0.012, every target met). A drifted map (noisy) still has 1.6-15 % (see the closing notes).
    unseen_side: bool = True
    side_min_agreement: float = Field(0.5, ge=0.0, le=1.0)
    unseen_side_cos: float = Field(0.3, ge=0.0, le=1.0)
    unseen_side_rgb: tuple[_Channel8, _Channel8, _Channel8] = (128, 128, 128)
    # visibility mode: the points a pixel's surfel averages lie this close behind its nearest one
    # (tighter still: a far wall's two faces, 0.1 m apart, must not average their colours).
    front_tolerance_m: float = Field(0.02, ge=0.0)
    front_tolerance_rel: float = Field(0.005, ge=0.0)
    # Occlusion tolerance epsilon = depth_tolerance_m + depth_tolerance_rel * min depth: surfaces
    # seen at grazing angles spread over more depth per pixel the farther they are.
    depth_tolerance_m: float = Field(0.10, ge=0.0)
    depth_tolerance_rel: float = Field(0.05, ge=0.0)
    near_m: float = Field(0.05, gt=0.0)
    far_m: float = Field(20.0, gt=0.0)
    cull: bool = True
    # Level of detail (None: every point in the frustum). The cost of a view then follows the
    # pixels it fills, not the density of the cloud or how far the map reaches.
    # "voxel" (:mod:`lod`): precomputed voxel-averaged levels per block; each block is drawn at the
    # coarsest level whose cell projects to at most lod_cell_px pixels at its nearest point.
    # "subsample": the first points of each (shuffled) block, lod_points_per_px per pixel it can cover.
    lod: Literal["voxel", "subsample"] | None = "voxel"
    # None: the mode's own (LOD_CELL_PX). The visibility mode sizes each footprint by its level's
    # spacing, so coarse cells cost it little: 2 px against 1 px (bench.anticipation, rgbd map,
    # every band): SSIM -0.005 at most, leak and holes equal, labels -0.2 points, for ~40 % fewer
    # points and 0.86x the time per view. 2.5 px against 2 (--full, rgbd maps of generated:0, the
    # 2-floor house and Replica, free poses and candidates): SSIM -0.011 at most, leak and holes
    # equal, labels -0.7 at most (generated:0 free poses > 2 m: 96.0 -> 95.3 %, the closest any
    # band comes to its target), for 0.70x the points and 0.91x the time per view on the 1e6 flat
    # (paired, one process), which brings that view within the speed target (3x one pass over
    # the cloud); 3 px: 0.88x, but SSIM -0.01 and labels -0.5 on the quick run already. The
    # paper's fixed 3x3 splat cannot close 2 px gaps, so it keeps 1 px.
    lod_cell_px: float | None = Field(None, gt=0.0, le=8.0)
    # Level 1's cell, each further level doubling it; halved for a cloud denser than this many
    # times its median point spacing (:func:`lod.first_cell_m`). Agent-built maps (~3 cm apart) keep
    # 4 cm; the 1e6-point built flat of bench.anticipation's speed line (1.2 cm apart) gets 2 cm:
    # 164 k -> 101 k points and 0.82x the CPU per view, SSIM -0.004 against the ray cast (40 views),
    # leak, holes and labels equal. (1.55 cm cells: as fast, SSIM -0.006.)
    lod_cell_m: float = Field(0.04, ge=0.005, le=1.0)
    lod_cell_spacings: float = Field(1.3, ge=1.0, le=8.0)
    lod_levels: int = Field(5, ge=1, le=8)
    lod_points_per_px: float | None = Field(6.0, gt=0.0)  # "subsample"; None: no LOD (either kind)
    # visibility mode, compiled path: blocks wholly behind the surfaces of the blocks nearer than
    # occlusion_near_m are not drawn (:mod:`occlusion`; the images are identical), in views that
    # draw at least occlusion_min_points after frustum culling and level of detail. Off: it culls
    # ~45 % of the drawn points (0.55 M -> 0.29-0.34 M per view in a 1,000 m2 three-storey
    # building, 0.15 -> 0.09 M on the generated:0 rgbd map), but a hidden point costs the front
    # pass only ~7.5 ns and the occluder (the near blocks projected, their quadrant covers) ~3 ms:
    # measured +8 % (building) and +19 % (rgbd map) CPU per view.
    occlusion_cull: bool = False
    occlusion_near_m: float = Field(3.0, gt=0.0)
    occlusion_min_points: int = Field(60_000, ge=0)
    # numpy backend: the per-point passes of ``layered`` run as compiled loops (numba) when it is
    # installed ("auto"), always ("numba": an error without it) or never ("numpy": array code).
    # Both give identical images; the compiled loops are ~5x faster.
    kernel: Literal["auto", "numba", "numpy"] = "auto"
    # numpy backend: views of one call rendered at once on this many threads (the compiled loops
    # and numpy's array loops release the GIL). Images do not depend on it.
    workers: int = Field(2, ge=1, le=64)


class TorchSplatConfig(SplatConfig):
    device: str = "auto"  # "auto" (cuda when present), "cpu", "cuda", "cuda:1", ...


@dataclass
class RenderedViews:
    """A batch of anticipated views, all (B, H, W[, 3])."""

    rgb: np.ndarray  # uint8 (B, H, W, 3); black in holes
    depth_m: np.ndarray  # float32 (B, H, W); z-depth, 0 in holes
    hole_mask: np.ndarray  # bool (B, H, W); True where no point reached the pixel
    labels: np.ndarray | None  # int32 (B, H, W); -1 in holes or when the cloud has no labels
    view_s: list[float] = field(default_factory=list)  # wall time per view (its own thread's)
    visible_points: list[int] = field(default_factory=list)  # points left after culling, per view
    batch_s: float = 0.0  # wall time of the whole call (views may overlap on several threads)

    @property
    def hole_fraction(self) -> float:
        return float(self.hole_mask.mean())


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


def point_spacing_of(index: IndexedCloud, neighbours: int) -> np.ndarray:
    """Per-point local spacing (float32 m, in the index's point order), cached on the index."""
    key = ("point-spacing", neighbours)
    if key not in index.cache:
        index.cache[key] = visibility.point_spacing(index.cloud.xyz, neighbours)
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
                index.cloud.xyz, spacing_neighbours, neighbours)
        else:
            index.cache[key] = visibility.point_normals(index.cloud.xyz, neighbours)
    return index.cache[key]


def point_sides_of(index: IndexedCloud, neighbours: int, spacing_neighbours: int | None,
                   min_agreement: float) -> tuple[np.ndarray, np.ndarray]:
    """(normals float32 (N, 3), sided uint8 (N,)) of the index's points, cached: the normals of
    :func:`point_normals_of`, turned towards the side each point was seen from where the map
    records it (:func:`visibility.orient_normals`); ``sided`` 0 where that side is not known."""
    key = ("point-sides", neighbours, min_agreement)
    if key not in index.cache:
        normals = point_normals_of(index, neighbours, spacing_neighbours)
        index.cache[key] = visibility.orient_normals(normals, index.cloud.view_dirs, min_agreement)
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


class _TorchOps:
    name = "torch"
    # torch parallelises inside each op (and a GPU serialises kernels): one view at a time.
    concurrent_views = False

    def __init__(self, device: str):
        import torch

        self.torch = torch
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise BackendUnavailableError(f"torch device {device!r} requested but CUDA is unavailable")
        self.device = torch.device(device)
        self._grids: dict = {}

    def asarray(self, a: np.ndarray):
        return self.torch.from_numpy(np.ascontiguousarray(a)).to(self.device)

    def to_numpy(self, a) -> np.ndarray:
        return a.detach().cpu().numpy()

    def full(self, n: int, value: float):
        return self.torch.full((n,), value, dtype=self.torch.float32, device=self.device)

    def scatter_min(self, n: int, idx, vals):
        out = self.full(n, math.inf)
        return out.scatter_reduce_(0, idx, vals, "amin", include_self=True)

    def scatter_max_int(self, n: int, idx, vals):
        out = self.torch.full((n,), -1, dtype=self.torch.int64, device=self.device)
        return out.scatter_reduce_(0, idx, vals, "amax", include_self=True)

    def scatter_add(self, n: int, idx, cols: Sequence):
        torch = self.torch
        src = torch.stack(list(cols), dim=1)
        out = torch.zeros((n, src.shape[1]), dtype=torch.float32, device=self.device)
        out.index_add_(0, idx, src)
        return list(out.unbind(1))

    def sum_in_order(self, n: int, idx, vals):
        # float32 sums as the numpy backend's, but index_add_ does not promise their order: the
        # backends agree within the tests' tolerance, not to the bit.
        out = self.torch.zeros(n, dtype=self.torch.float32, device=self.device)
        return out.index_add_(0, idx, vals.to(self.torch.float32))

    def accumulate_front(self, n: int, q, front, z, arrays: _CloudArrays, idx, qu, qv, spacing=None,
                         unseen=None, unseen_rgb=(0, 0, 0)):
        torch = self.torch
        lq = q[front]
        pts = idx[front]
        rgb = arrays.rgb[pts]
        if unseen is not None:
            rgb = torch.where(unseen[front, None], torch.tensor(unseen_rgb, dtype=rgb.dtype, device=self.device), rgb)
        cols = [z[front, None], rgb, qu[front, None], qv[front, None]]
        if spacing is not None:
            cols.append(spacing[front, None])
        src = torch.cat(cols, dim=1)
        out = torch.zeros((n, src.shape[1]), dtype=torch.float32, device=self.device)
        out.index_add_(0, lq, src)
        cnt = torch.bincount(lq, minlength=n).to(torch.float32)
        s_sp = None if spacing is None else out[:, 6]
        return cnt, out[:, 0], [out[:, 1], out[:, 2], out[:, 3]], out[:, 4], out[:, 5], s_sp

    def floor_int(self, x):
        return self.torch.floor(x).to(self.torch.int64)

    def rint(self, x):
        return self.torch.round(x)

    def exp(self, x):
        return self.torch.exp(x)

    def minimum(self, a, b):
        return self.torch.minimum(a, b)

    def where(self, c, a, b):
        torch = self.torch
        if not isinstance(a, torch.Tensor):
            a = torch.as_tensor(a, dtype=b.dtype, device=self.device)
        if not isinstance(b, torch.Tensor):
            b = torch.as_tensor(b, dtype=a.dtype, device=self.device)
        return torch.where(c, a, b)

    def cat(self, parts):
        return self.torch.cat(parts)

    def stack(self, parts):
        return self.torch.stack(list(parts))

    def clamp(self, x, lo, hi):
        return x.clamp(lo, hi)

    def to_int64(self, x):
        return x.to(self.torch.int64)

    def as_f32(self, mask):
        return mask.to(self.torch.float32)

    def floor(self, x):
        return self.torch.floor(x)

    def sqrt(self, x):
        return self.torch.sqrt(x)

    def abs(self, x):
        return self.torch.abs(x)

    def maximum(self, a, b):
        return self.torch.maximum(a, b)

    def max_value(self, x) -> float:
        return float(x.max())

    def any(self, x) -> bool:
        return bool(x.any())

    def full2(self, h: int, w: int, value: float):
        return self.torch.full((h, w), value, dtype=self.torch.float32, device=self.device)

    def pad_ring(self, a, value):
        return self.torch.nn.functional.pad(a[None, None], (1, 1, 1, 1), value=value)[0, 0]

    def pad2(self, a, top: int, bottom: int, left: int, right: int, value):
        if not (top or bottom or left or right):
            return a
        h, w = a.shape
        out = self.torch.full((top + h + bottom, left + w + right), value, dtype=a.dtype, device=self.device)
        out[top : top + h, left : left + w] = a
        return out

    def ceil(self, x):
        return self.torch.ceil(x)

    def erode(self, x, r: int):
        f = self.torch.nn.functional
        return -f.max_pool2d(-x[None, None], 2 * r + 1, 1, r)[0, 0]

    def erode_quadrant(self, x, m: int, sy: int, sx: int):
        f = self.torch.nn.functional
        # Pad by m on the window's side, then a min-pool of (m + 1) x (m + 1) with stride 1.
        padding = (m if sx < 0 else 0, 0 if sx < 0 else m, m if sy < 0 else 0, 0 if sy < 0 else m)
        xp = f.pad(-x[None, None], padding, value=-math.inf)
        return -f.max_pool2d(xp, m + 1, 1)[0, 0]

    def index_grid(self, h: int, w: int, axis: int):
        key = (h, w, axis)
        if key not in self._grids:
            self._grids[key] = self.asarray(_index_grid(h, w, axis))
        return self._grids[key]

    def nonzero2(self, mask):
        r, c = self.torch.nonzero(mask, as_tuple=True)
        return r, c

    def lookup(self, table: np.ndarray, index):
        return self.asarray(table)[index.to(self.torch.int64)]

    def unique_values(self, x) -> list[float]:
        return self.torch.unique(x).tolist()

    def children(self, a):
        h, w = a.shape
        return a.reshape(h // 2, 2, w // 2, 2).permute(1, 3, 0, 2).reshape(4, h // 2, w // 2)


    def cloud_arrays(self, index: IndexedCloud, cloud=None, tag=()) -> _CloudArrays:
        key = ("torch-arrays", str(self.device), *tag)
        if key not in index.cache:
            c = index.cloud if cloud is None else cloud
            xyz = self.asarray(c.xyz)
            index.cache[key] = _CloudArrays(
                xyz[:, 0].contiguous(),
                xyz[:, 1].contiguous(),
                xyz[:, 2].contiguous(),
                self.asarray(c.rgb.astype(np.float32)),
                None if c.labels is None else self.asarray(c.labels),
            )
        return index.cache[key]


# --- the renderer ---------------------------------------------------------------------------------


class SplatRenderer:
    """Renders anticipated views of an :class:`IndexedCloud`; create through ``RENDERERS``."""

    def __init__(self, config: SplatConfig, ops):
        if config.far_m <= config.near_m:
            raise ValueError(f"far_m ({config.far_m}) must exceed near_m ({config.near_m})")
        self.config = config
        self._ops = ops
        # The compiled loops implement the numpy backend's ``layered`` passes; ``exact`` (the
        # reference) and torch always run as array code.
        self._use_kernel = (
            ops.name == "numpy" and (config.mode == "visibility" or config.algorithm == "layered")
            and config.kernel != "numpy" and kernels.AVAILABLE
        )
        if config.kernel == "numba" and not kernels.AVAILABLE:
            raise BackendUnavailableError("kernel 'numba' requested but numba is not installed")
        self._pool: ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()

    def _view_pool(self) -> ThreadPoolExecutor:
        """The worker threads of ``render_poses``, started at the first batch and kept: a pool per
        call cost ~0.35 ms of thread starts and joins per step. Its threads end with the renderer."""
        with self._pool_lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.config.workers, thread_name_prefix="splat")
                weakref.finalize(self, self._pool.shutdown, wait=False)
            return self._pool

    @property
    def backend(self) -> str:
        return self._ops.name

    @property
    def device(self) -> str:
        return str(getattr(self._ops, "device", "cpu"))

    @property
    def kernel(self) -> str:
        """``"numba"`` when the per-point passes run compiled, else ``"array"``."""
        return "numba" if self._use_kernel else "array"

    def warm_up(self) -> float:
        """Compile the kernels now (a one-off per process, ~1-3 s, or well under a second from
        numba's disk cache) so that the first request does not pay for it; returns seconds spent."""
        return kernels.warm_up() if self._use_kernel else 0.0

    def prepare(self, index: IndexedCloud) -> float:
        """Build this renderer's per-map data now (the backend's arrays and, in the visibility
        mode, the per-point spacing) so that no request pays for it; returns seconds spent. A
        map loader calls it once per map version; rendering without it computes the same lazily."""
        t0 = time.perf_counter()
        self._drawn(index)
        return time.perf_counter() - t0

    @property
    def _with_slope(self) -> bool:
        """Whether views use the slope-scaled visibility tolerance (the map's normals)."""
        return self.config.mode == "visibility" and self.config.visibility_slope_px > 0

    def _with_sides(self, index: IndexedCloud) -> bool:
        """Whether views draw the side of a surface the robot never saw as unseen (the map records
        where its points were seen from)."""
        cfg = self.config
        return cfg.mode == "visibility" and cfg.unseen_side and index.cloud.view_dirs is not None

    def _normals_of(self, index: IndexedCloud) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(normals, sided or None) of the index's points as views need them, or None."""
        cfg = self.config
        if self._with_sides(index):
            return point_sides_of(index, cfg.normal_neighbours, cfg.spacing_neighbours, cfg.side_min_agreement)
        if self._with_slope:
            return point_normals_of(index, cfg.normal_neighbours, cfg.spacing_neighbours), None
        return None

    def _voxel_lod(self, index: IndexedCloud) -> VoxelLod | None:
        cfg = self.config
        if cfg.lod != "voxel" or cfg.lod_points_per_px is None:
            return None
        normals = self._normals_of(index)
        nn = None if normals is None else (cfg.normal_neighbours,
                                           cfg.side_min_agreement if normals[1] is not None else None)
        key = ("voxel-lod", cfg.lod_cell_m, cfg.lod_cell_spacings, cfg.lod_levels, cfg.spacing_neighbours, nn)
        if key not in index.cache:
            spacing = point_spacing_of(index, cfg.spacing_neighbours)
            cell_m = first_cell_m(spacing, cfg.lod_cell_m, cfg.lod_cell_spacings)
            index.cache[key] = build_voxel_lod(index, spacing, cell_m, cfg.lod_levels,
                                               *(normals if normals is not None else (None, None)))
        return index.cache[key]

    def _drawn(self, index: IndexedCloud):
        """(backend arrays, per-point spacing or None, :class:`_Normals` or None, voxel LOD or None)
        of the cloud this renderer draws: the index's points, followed by their voxel levels with
        ``lod="voxel"``."""
        cfg = self.config
        lod = self._voxel_lod(index)
        with_spacing = cfg.mode == "visibility" or lod is not None
        if lod is None:
            arrays = self._ops.cloud_arrays(index)
            normals, sided = self._normals_of(index) or (None, None)
            spacing = point_spacing_of(index, cfg.spacing_neighbours) if with_spacing else None
            tag = ("points",)
        else:
            arrays = self._ops.cloud_arrays(index, lod.cloud, ("voxel-lod", lod.cell_m))
            spacing = lod.spacing
            normals, sided = lod.normals, lod.sided
            tag = ("voxel-lod", lod.cell_m)
        drawn_normals = None
        if normals is not None:
            key = ("normal-columns", self._ops.name, self.device, *tag, cfg.normal_neighbours,
                   None if sided is None else cfg.side_min_agreement)
            if key not in index.cache:
                cols = tuple(self._ops.asarray(np.ascontiguousarray(normals[:, k])) for k in range(3))
                index.cache[key] = _Normals(cols, None if sided is None else self._ops.asarray(sided))
            drawn_normals = index.cache[key]
        return arrays, spacing, drawn_normals, lod

    def _runs(self, index: IndexedCloud, lod: VoxelLod | None, wfc: np.ndarray, cam: PinholeCamera,
              frustum: Frustum) -> _Runs:
        """The runs of the drawn cloud one view walks: culled blocks, at their level of detail."""
        cfg = self.config
        mask = index.visible_blocks(wfc, frustum) if cfg.cull else None
        if lod is not None:
            cell_px = cfg.lod_cell_px if cfg.lod_cell_px is not None else LOD_CELL_PX[cfg.mode]
            starts, counts = lod.select(index, mask, wfc, cam.fx, cell_px)
            return _Runs(starts, counts, np.ones(len(starts), np.float32))
        full = index.counts if mask is None else index.counts[mask]
        starts = index.starts if mask is None else index.starts[mask]
        if cfg.lod == "subsample" and cfg.lod_points_per_px is not None:
            kept = index.lod_counts(wfc, cam.fx, cfg.lod_points_per_px)
            kept = kept if mask is None else kept[mask]
            # Level of detail widens the spacing of the points it keeps by sqrt(all / kept).
            return _Runs(starts, kept, np.sqrt(full / np.maximum(kept, 1)).astype(np.float32))
        return _Runs(starts, full, np.ones(len(starts), np.float32))

    def render(
        self,
        index: IndexedCloud,
        views: Sequence[ViewPose],
        camera: CameraIntrinsics | PinholeCamera | None = None,
        camera_height_m: float = DEFAULT_CAMERA_HEIGHT_M,
        with_labels: bool = True,
    ) -> RenderedViews:
        """Render every view of one step in one call (the map's arrays are shared between views).

        ``views`` are agent poses (floor point, heading, pitch); the camera sits
        ``camera_height_m`` above the floor point.
        """
        cam = _pinhole(camera)
        poses = [
            camera_pose(v.position_m, v.heading_rad, v.pitch_rad, camera_height_m) for v in views
        ]
        return self.render_poses(index, poses, cam, with_labels)

    def render_poses(
        self,
        index: IndexedCloud,
        world_from_cameras: Sequence[np.ndarray],
        camera: CameraIntrinsics | PinholeCamera | None = None,
        with_labels: bool = True,
    ) -> RenderedViews:
        """Render from explicit 4x4 world_from_camera matrices (OpenCV camera axes).

        With the numpy backend, up to ``config.workers`` views render at once on threads; every
        view writes only its own slice of the output, so the images do not depend on it."""
        t_batch = time.perf_counter()
        cam = _pinhole(camera)
        cfg = self.config
        frustum = Frustum.for_camera(cam, cfg.near_m, cfg.far_m)
        labelled = with_labels and index.cloud.labels is not None
        b, h, w = len(world_from_cameras), cam.height_px, cam.width_px
        out = RenderedViews(
            rgb=np.zeros((b, h, w, 3), np.uint8),
            depth_m=np.zeros((b, h, w), np.float32),
            hole_mask=np.ones((b, h, w), bool),
            labels=np.full((b, h, w), -1, np.int32) if labelled else None,
        )
        arrays, spacing, normals, lod = self._drawn(index)
        poses = [np.asarray(m, float) for m in world_from_cameras]
        # What each view draws, first (frustum culling and level of detail: ~40 us a view): the
        # views then go to the threads costliest first, by the points they draw, so that a long
        # view does not start last beside an idle thread (longest-processing-time-first; a step
        # of six views on two threads: batch / half the views' sum 1.13 -> 1.09, wall 0.94x).
        all_runs = [self._runs(index, lod, wfc, cam, frustum) for wfc in poses]

        def one(i: int) -> tuple[int, float]:
            t0 = time.perf_counter()
            wfc, runs = poses[i], all_runs[i]
            if self._cull_occlusion:
                runs = self._occlusion(index, lod, arrays, spacing, runs, wfc, cam)
            (rgb, depth, hole, labels), n = self._render_one(arrays, spacing, normals, runs, wfc, cam, labelled)
            out.rgb[i], out.depth_m[i], out.hole_mask[i] = rgb, depth, hole
            if labelled:
                out.labels[i] = labels
            return n, time.perf_counter() - t0

        workers = min(cfg.workers, b) if self._ops.concurrent_views else 1
        if workers > 1:
            order = sorted(range(b), key=lambda i: -int(all_runs[i].counts.sum()))
            done = dict(zip(order, self._view_pool().map(one, order)))
            done = [done[i] for i in range(b)]
        else:
            done = [one(i) for i in range(b)]
        out.visible_points = [n for n, _ in done]
        out.view_s = [dt for _, dt in done]
        out.batch_s = time.perf_counter() - t_batch
        return out

    @property
    def _cull_occlusion(self) -> bool:
        """Occlusion culling runs where the visibility test it relies on runs compiled; the array
        paths (numpy reference, torch) draw every block, with the same images."""
        return self.config.occlusion_cull and self.config.mode == "visibility" and self._use_kernel

    def _occlusion(self, index: IndexedCloud, lod: VoxelLod | None, arrays, spacing, runs: _Runs,
                   wfc: np.ndarray, cam: PinholeCamera) -> _Runs:
        """``runs`` without the runs wholly behind the near ones' surfaces (:mod:`occlusion`)."""
        cfg = self.config
        if int(runs.counts.sum()) < cfg.occlusion_min_points:
            return runs
        key = ("occlusion-runs", "voxel" if lod is not None else "points", cfg.lod_cell_m, cfg.lod_cell_spacings,
               cfg.lod_levels, cfg.spacing_neighbours)
        if key not in index.cache:
            starts, counts = (lod.starts, lod.counts) if lod is not None else (index.starts, index.counts)
            index.cache[key] = occlusion.run_table(starts, counts, spacing, index.block_count)
        f = float(cam.fx)
        slope = 0.0
        if self._with_slope:
            slope = cfg.visibility_slope_px * math.tan(math.radians(cfg.visibility_max_incidence_deg)) / f
        rel1, tol = self._front_tolerance()
        params = occlusion.OcclusionParams(
            near_m=cfg.occlusion_near_m, min_points=cfg.occlusion_min_points, focal_px=f,
            footprint_scale=cfg.footprint_scale, min_radius_px=min(cfg.min_radius_px, cfg.max_radius_px),
            max_radius_px=cfg.max_radius_px, front_rel1=float(rel1), front_tol_m=float(tol),
            vis_rel1=float(np.float32(1.0 + cfg.visibility_tolerance_rel)), vis_tol_m=cfg.visibility_tolerance_m,
            slope_per_m=slope, near_clip_m=cfg.near_m, far_clip_m=cfg.far_m)
        lut = visibility.radius_lut(self._visibility_params(cam))
        proj = (cam.matrix() @ np.linalg.inv(wfc)[:3]).astype(np.float32)
        keep = occlusion.cull(arrays.x, arrays.y, arrays.z, spacing, runs.starts, runs.counts, runs.scale,
                              index.cache[key], index.block_min, index.block_max, proj, wfc, cam.matrix(),
                              cam.height_px, cam.width_px, lut, params, self._pad)
        if keep.all():
            return runs
        return _Runs(runs.starts[keep], runs.counts[keep], runs.scale[keep])

    def _render_one(self, arrays, spacing, normals, runs: _Runs, wfc: np.ndarray, cam: PinholeCamera,
                    labelled: bool):
        """One view from the points of ``runs``. Returns ((rgb, depth, hole, labels), number of
        points rendered)."""
        cfg = self.config
        h, w = cam.height_px, cam.width_px
        # Rows of K [R^T | -R^T t]: one affine map per image coordinate, evaluated elementwise (not
        # as a matmul) so that numpy, torch and the kernels round identically.
        proj = (cam.matrix() @ np.linalg.inv(wfc)[:3]).astype(np.float32)
        if cfg.mode == "paper" and cfg.algorithm == "exact":
            return self._paper_exact(arrays, runs, proj, h, w, labelled)
        slope = None if normals is None else _SlopeView(normals.columns, self._slope_constants(wfc, cam),
                                                        normals.sided)
        front = self._front_kernel(arrays, spacing, slope, runs, proj, h, w, labelled) if self._use_kernel else None
        if front is None:
            front = self._front_arrays(arrays, spacing, slope, runs, proj, h, w, labelled)
        if front.n == 0:
            return _empty(h, w), 0
        if cfg.mode == "paper":
            return self._paper_compose(arrays, front, h, w, labelled), front.n
        return self._visibility_compose(arrays, front, cam, h, w, labelled), front.n

    def _slope_constants(self, wfc: np.ndarray, cam: PinholeCamera) -> np.ndarray:
        """float32 (8,): camera centre (world), optical axis (world), 1 / focal (px), and
        1 / tan(max incidence): what :func:`_point_slope` needs of a view."""
        cfg = self.config
        inv_tan = 1.0 / math.tan(math.radians(cfg.visibility_max_incidence_deg))
        return np.array([*wfc[:3, 3], *wfc[:3, 2], 1.0 / cam.fx, inv_tan], np.float32)

    def _front_tolerance(self) -> tuple[np.float32, np.float32]:
        """(1 + relative, absolute) depth tolerance of a pixel's front layer in this mode."""
        cfg = self.config
        if cfg.mode == "visibility":
            return np.float32(1.0 + cfg.front_tolerance_rel), np.float32(cfg.front_tolerance_m)
        return np.float32(1.0 + cfg.depth_tolerance_rel), np.float32(cfg.depth_tolerance_m)

    def _front_kernel(self, arrays, spacing, slope: _SlopeView | None, runs: _Runs, proj, h, w,
                      labelled) -> _Front | None:
        """The front layer from the compiled loops; None when a pixel overflows them."""
        cfg = self.config
        n = int(runs.counts.sum())
        if n == 0:
            return _Front(n=0)
        with_spacing = cfg.mode == "visibility"
        spacing = spacing if with_spacing else np.zeros(1, np.float32)
        no_normal = np.zeros(1, np.float32)
        nx, ny, nz = slope.normals if slope is not None else (no_normal, no_normal, no_normal)
        consts = slope.constants if slope is not None else np.zeros(8, np.float32)
        with_slope = slope is not None and self._with_slope
        with_sides = slope is not None and slope.sided is not None
        zbuf, acc, uv, overflow = kernels.front_pass(
            arrays.x, arrays.y, arrays.z, arrays.rgb_u32, spacing, runs.starts, runs.counts, runs.scale, proj.ravel(),
            np.float32(cfg.near_m), np.float32(cfg.far_m), w, h, *self._front_tolerance(), labelled, with_spacing,
            nx, ny, nz, consts, with_slope, cfg.mode == "paper", self._pad,
            slope.sided if with_sides else np.zeros(1, np.uint8), np.float32(cfg.unseen_side_cos), with_sides,
            kernels.pack_rgb(np.asarray([cfg.unseen_side_rgb], np.uint8))[0],
        )
        if overflow:
            log.debug("a pixel's front layer exceeds %d points: array code for this view", kernels.MAX_FRONT_POINTS)
            return None
        # Columns of the kernel's one row per pixel (strided views, no copies).
        return _Front(n, zbuf, acc[:, 0], acc[:, 1], [acc[:, 2], acc[:, 3], acc[:, 4]], uv[0], uv[1],
                      acc[:, 5] if with_spacing else None, acc.view(np.int32)[:, 7] if labelled else None,
                      acc[:, 6] if with_slope else None)

    @property
    def _pad(self) -> int:
        """Pixels on each side of the image that a view's points are projected into: the 3x3
        splat's ring, and in the visibility mode the guard band of its footprints as well."""
        return 1 + (self.config.guard_px if self.config.mode == "visibility" else 0)

    def _project(self, arrays, idx, proj, h, w, pad=1):
        """Depth, target pixel of the image padded by ``pad`` (the miss bin for points off it or
        out of range) and the quantised sub-pixel offsets of the points ``idx``."""
        ops, cfg = self._ops, self.config
        wp, npad = w + 2 * pad, (h + 2 * pad) * (w + 2 * pad)
        x, y, zw = arrays.x[idx], arrays.y[idx], arrays.z[idx]
        (a0, a1, a2, a3), (b0, b1, b2, b3), (c0, c1, c2, c3) = ([float(v) for v in row] for row in proj)
        z = x * c0 + y * c1 + zw * c2 + c3
        with np.errstate(divide="ignore", invalid="ignore"):  # z = 0: masked out just below
            inv = 1.0 / z
            u = (x * a0 + y * a1 + zw * a2 + a3) * inv
            v = (x * b0 + y * b1 + zw * b2 + b3) * inv
        iu = ops.floor_int(u + 0.5)
        iv = ops.floor_int(v + 0.5)
        valid = (z > cfg.near_m) & (z < cfg.far_m) & (iu >= -pad) & (iu <= w - 1 + pad) & (iv >= -pad) & (iv <= h - 1 + pad)
        q = ops.where(valid, (iv + pad) * wp + (iu + pad), npad)
        z = ops.where(valid, z, math.inf)
        # Sub-pixel offsets of each point from its pixel centre, quantised to 1/255 px so that
        # the backends' sums agree exactly (and numpy can pack them into one exact float64 sum).
        qu = ops.rint(ops.clamp(u - iu + 0.5, 0.0, 1.0) * 255.0)
        qv = ops.rint(ops.clamp(v - iv + 0.5, 0.0, 1.0) * 255.0)
        return z, q, qu, qv

    def _front_arrays(self, arrays, spacing, slope: _SlopeView | None, runs: _Runs, proj, h, w,
                      labelled) -> _Front:
        """The front layer as array code (numpy or torch): the reference of the compiled loops."""
        ops, cfg = self._ops, self.config
        pad = self._pad
        npad = (h + 2 * pad) * (w + 2 * pad)
        idx_np = runs.indices()
        n = len(idx_np)
        if n == 0:
            return _Front(n=0)
        idx = ops.asarray(idx_np)
        z, q, qu, qv = self._project(arrays, idx, proj, h, w, pad)
        zbuf = ops.scatter_min(npad + 1, q, z)
        sp = None
        if cfg.mode == "visibility":
            sp = ops.asarray(spacing[idx_np] * np.repeat(runs.scale, runs.counts))
        # The front layer of each pixel: its points within epsilon of the pixel's own nearest.
        rel1, tol = self._front_tolerance()
        front = z <= zbuf[q] * float(rel1) + float(tol)
        unseen = None
        if slope is not None and slope.sided is not None:
            unseen = _unseen_side(ops, arrays.x[idx], arrays.y[idx], arrays.z[idx], *(c[idx] for c in slope.normals),
                                  slope.sided[idx], slope.constants, self.config.unseen_side_cos)
        cnt, s_z, s_rgb, s_u, s_v, s_sp = ops.accumulate_front(npad + 1, q, front, z, arrays, idx, qu, qv, sp,
                                                               unseen, self.config.unseen_side_rgb)
        best = None
        if labelled:
            # Nearest point per source pixel (largest point id among exact ties, so every path agrees).
            nearest = z == zbuf[q]
            best = ops.scatter_max_int(npad + 1, q[nearest], idx[nearest])
        s_g = None
        if slope is not None and self._with_slope:
            pts = idx[front]
            # Points off the image are "front" in the miss bin (depth inf): nan there, never read.
            with np.errstate(invalid="ignore"):
                g = _point_slope(ops, arrays.x[pts], arrays.y[pts], arrays.z[pts], z[front],
                                 *(c[pts] for c in slope.normals), slope.constants)
            s_g = ops.sum_in_order(npad + 1, q[front], g)
        return _Front(n, zbuf, cnt, s_z, s_rgb, s_u, s_v, s_sp, best, s_g)

    def _labels_pad(self, arrays, best, h, w, pad=1):
        """The nearest point's label per pixel of the image padded by ``pad`` (-1 where none)."""
        ops = self._ops
        best_pt = best[: (h + 2 * pad) * (w + 2 * pad)].reshape(h + 2 * pad, w + 2 * pad)
        if self._use_kernel:
            return kernels.labels_of(best_pt, arrays.labels)
        return ops.where(best_pt >= 0, ops.to_int64(arrays.labels[ops.clamp(best_pt, 0, None)]), -1)

    def _paper_compose(self, arrays, front: _Front, h, w, labelled):
        """The paper's 3x3 Gaussian splat of the front-layer surfels (``layered``)."""
        ops, cfg = self._ops, self.config
        hp, wp = h + 2, w + 2
        zpad = front.zbuf[: hp * wp].reshape(hp, wp)
        rel1, tol = np.float32(1.0 + cfg.depth_tolerance_rel), np.float32(cfg.depth_tolerance_m)
        if self._use_kernel and ops.name == "numpy":
            chans, gx, gy = self._surfels(front.cnt, front.s_z, front.s_rgb, front.s_u, front.s_v, h, w)
            lab_pad = self._labels_pad(arrays, front.best, h, w) if labelled else np.empty((0, 0), np.int64)
            rgb_img = np.empty((h, w, 3), np.uint8)
            depth = np.empty((h, w), np.float32)
            hole = np.empty((h, w), bool)
            labels = np.empty((h, w), np.int32) if labelled else None
            kernels.compose(
                chans, np.stack([gx[-1], gx[0], gx[1]]), np.stack([gy[-1], gy[0], gy[1]]), zpad, lab_pad, rel1, tol,
                rgb_img, depth, hole, labels if labelled else np.empty((0, 0), np.int32), labelled,
            )
            return rgb_img, depth, hole, labels
        thr = self._threshold(zpad, h, w)
        acc = self._layered(front.cnt, front.s_z, front.s_rgb, front.s_u, front.s_v, zpad, thr, h, w)
        return self._finish(acc, zpad, self._labels_pad(arrays, front.best, h, w) if labelled else None, h, w)

    def _paper_exact(self, arrays, runs: _Runs, proj, h, w, labelled):
        """The paper's 3x3 splat point by point (``exact``, the reference of ``layered``)."""
        ops, cfg = self._ops, self.config
        npad = (h + 2) * (w + 2)
        idx_np = runs.indices()
        if len(idx_np) == 0:
            return _empty(h, w), 0
        idx = ops.asarray(idx_np)
        z, q, qu, qv = self._project(arrays, idx, proj, h, w)
        zbuf = ops.scatter_min(npad + 1, q, z)
        zpad = zbuf[:npad].reshape(h + 2, w + 2)
        lab_pad = None
        if labelled:
            nearest = z == zbuf[q]
            lab_pad = self._labels_pad(arrays, ops.scatter_max_int(npad + 1, q[nearest], idx[nearest]), h, w)
        thr = self._threshold(zpad, h, w)
        acc = self._exact(arrays, idx, z, q, qu, qv, thr, 1.0 / (2.0 * cfg.kernel_sigma_px**2), h, w)
        return self._finish(acc, zpad, lab_pad, h, w), len(idx_np)

    def _threshold(self, zpad, h, w):
        """Occlusion threshold per pixel: epsilon behind the 3x3 minimum depth."""
        ops, cfg = self._ops, self.config
        zmin = None
        for oy, ox in _OFFSETS:
            sl = zpad[1 - oy : 1 - oy + h, 1 - ox : 1 - ox + w]
            zmin = sl if zmin is None else ops.minimum(zmin, sl)
        return zmin * (1.0 + cfg.depth_tolerance_rel) + cfg.depth_tolerance_m

    def _finish(self, acc, zpad, lab_pad, h, w):
        """Normalise the accumulated splats; the label of the nearest source among the nine."""
        ops = self._ops
        acc_w = acc[0]
        hole = ~(acc_w > 0)
        safe = ops.where(hole, 1.0, acc_w)
        depth = ops.where(hole, 0.0, acc[1] / safe)
        rgb = ops.where(hole[None], 0.0, acc[2:5] / safe[None])
        labels = None
        if lab_pad is not None:
            best = None
            for oy, ox in _OFFSETS:
                zs_ = zpad[1 - oy : 1 - oy + h, 1 - ox : 1 - ox + w]
                ls_ = lab_pad[1 - oy : 1 - oy + h, 1 - ox : 1 - ox + w]
                if best is None:
                    best, labels = zs_, ls_
                else:
                    closer = zs_ < best
                    best = ops.where(closer, zs_, best)
                    labels = ops.where(closer, ls_, labels)
            labels = ops.to_numpy(ops.where(hole, -1, labels)).astype(np.int32)
        return _images(ops, rgb, depth, hole, labels)

    def _visibility_compose(self, arrays, front: _Front, cam: PinholeCamera, h, w, labelled):
        """Footprints, visibility and pull-push filling of the front-layer surfels (:mod:`visibility`)."""
        ops, cfg = self._ops, self.config
        pad = self._pad
        hp, wp = h + 2 * pad, w + 2 * pad
        npad = hp * wp

        def img(a):
            return a[:npad].reshape(hp, wp)

        # The compiled path reads each visible pixel's label through its nearest point's id: a
        # label image of every pixel of the guard-band grid costs a pass it does not need.
        compiled = self._use_kernel
        layer = visibility.FrontLayer(
            zmin=img(front.zbuf), count=img(front.cnt), sum_z=img(front.s_z), sum_rgb=[img(c) for c in front.s_rgb],
            sum_spacing=img(front.s_sp),
            label=self._labels_pad(arrays, front.best, h, w, pad) if labelled and not compiled else None,
            sum_slope=None if front.s_g is None else img(front.s_g),
        )
        params = self._visibility_params(cam)
        if compiled:
            nearest = img(front.best) if labelled else None
            rgb, depth, hole, labels = visibility.compose_compiled(layer, params, h, w, nearest,
                                                                   arrays.labels if labelled else None)
            return (visibility_kernels.rgb8(rgb), depth, hole,
                    None if labels is None else labels.astype(np.int32))
        rgb, depth, hole, labels = visibility.compose(ops, layer, params, h, w)
        if labels is not None:
            labels = ops.to_numpy(labels).astype(np.int32)
        return _images(ops, rgb, depth, hole, labels)

    def _visibility_params(self, cam: PinholeCamera) -> visibility.VisibilityParams:
        cfg = self.config
        return visibility.VisibilityParams(
            focal_px=float(cam.fx), footprint_scale=cfg.footprint_scale, max_radius_px=cfg.max_radius_px,
            min_radius_px=min(cfg.min_radius_px, cfg.max_radius_px),
            gap_levels=cfg.gap_levels, fill_levels=cfg.fill_levels, gap_max_m=cfg.gap_max_m,
            tol_rel1=float(np.float32(1.0 + cfg.visibility_tolerance_rel)), tol_abs_m=cfg.visibility_tolerance_m,
            slope_per_px=math.tan(math.radians(cfg.fill_slope_deg)) / float(cam.fx),
            filter_rel=cfg.colour_filter_rel, slope_px=cfg.visibility_slope_px, guard_px=self._pad - 1,
            depth_step_m=cfg.far_m / visibility.COVER_MAX_CODE,
        )

    def _surfels(self, cnt, s_z, s_rgb, s_u, s_v, h, w):
        """Per source pixel: the five summed channels (count, depth, r, g, b) as (5, H+2, W+2) and
        the separable Gaussian factors of the surfel's mean offset towards each neighbour."""
        ops, cfg = self._ops, self.config
        hp, wp = h + 2, w + 2
        npad = hp * wp
        inv2s2 = 1.0 / (2.0 * cfg.kernel_sigma_px**2)
        safe = ops.where(cnt > 0, cnt, 1.0)
        # Mean sub-pixel position of the surfel, in pixels from its pixel centre.
        mu = (s_u / safe)[:npad].reshape(hp, wp) / 255.0 - 0.5
        mv = (s_v / safe)[:npad].reshape(hp, wp) / 255.0 - 0.5
        chans = ops.stack([cnt[:npad], s_z[:npad], s_rgb[0][:npad], s_rgb[1][:npad], s_rgb[2][:npad]])
        chans = chans.reshape(5, hp, wp)
        # The Gaussian is separable: three horizontal and three vertical factors cover nine offsets.
        gx = {ox: ops.exp(-((mu - ox) ** 2) * inv2s2) for ox in (-1, 0, 1)}
        gy = {oy: ops.exp(-((mv - oy) ** 2) * inv2s2) for oy in (-1, 0, 1)}
        return chans, gx, gy

    def _layered(self, cnt, s_z, s_rgb, s_u, s_v, zpad, thr, h, w):
        """Splat the per-pixel front-layer surfels over their 3x3 neighbourhoods (image space)."""
        chans, gx, gy = self._surfels(cnt, s_z, s_rgb, s_u, s_v, h, w)
        acc = None
        for oy, ox in _OFFSETS:
            r0, c0 = 1 - oy, 1 - ox
            k = gx[ox][r0 : r0 + h, c0 : c0 + w] * gy[oy][r0 : r0 + h, c0 : c0 + w]
            k = k * (zpad[r0 : r0 + h, c0 : c0 + w] <= thr)
            term = chans[:, r0 : r0 + h, c0 : c0 + w] * k[None]
            acc = term if acc is None else acc + term
        return acc

    def _exact(self, arrays, idx, z, q, qu, qv, thr, inv2s2, h, w):
        ops = self._ops
        wp = w + 2
        npad = (h + 2) * wp
        # Per-target thresholds; the padding ring and the miss bin stay -inf so nothing lands there.
        tpad = ops.full(npad + 1, -math.inf)
        tpad[:npad].reshape(h + 2, wp)[1 : 1 + h, 1 : 1 + w] = thr
        fu = qu / 255.0 - 0.5
        fv = qv / 255.0 - 0.5
        rgb = arrays.rgb[idx]
        tgt, wts, pts = [], [], []
        arange = ops.asarray(np.arange(z.shape[0], dtype=np.int64))
        for oy, ox in _OFFSETS:
            t_idx = ops.clamp(q + (oy * wp + ox), 0, npad)
            ok = z <= tpad[t_idx]
            k = ops.exp(-((fu[ok] - ox) ** 2 + (fv[ok] - oy) ** 2) * inv2s2)
            tgt.append(t_idx[ok])
            wts.append(k)
            pts.append(arange[ok])
        t_all, k_all, p_all = ops.cat(tgt), ops.cat(wts), ops.cat(pts)
        c = rgb[p_all]
        sums = ops.scatter_add(
            npad, t_all, [k_all, k_all * z[p_all], k_all * c[:, 0], k_all * c[:, 1], k_all * c[:, 2]]
        )
        return ops.stack([s.reshape(h + 2, wp)[1 : 1 + h, 1 : 1 + w] for s in sums])


@dataclass(frozen=True)
class _Runs:
    """What one view draws: points ``starts[r] : starts[r] + counts[r]`` of the drawn cloud, whose
    spacing level of detail widens by ``scale[r]``."""

    starts: np.ndarray  # int64
    counts: np.ndarray  # int64
    scale: np.ndarray  # float32

    def indices(self) -> np.ndarray:
        """The points of every run, int64, in run order."""
        total = int(self.counts.sum())
        if total == 0:
            return np.empty(0, dtype=np.int64)
        shift = self.starts - (np.cumsum(self.counts) - self.counts)
        return np.repeat(shift, self.counts) + np.arange(total, dtype=np.int64)


@dataclass(frozen=True)
class _Normals:
    """The drawn cloud's normals as three contiguous float32 columns (backend arrays), and which
    points' normals point towards the side the robot saw them from (uint8 / bool, or None: the
    map does not say)."""

    columns: tuple
    sided: object | None = None


@dataclass(frozen=True)
class _SlopeView:
    """What the slope-scaled tolerance and the side test need of a view: the drawn cloud's normals
    and sides (:class:`_Normals`) and the view's constants (:meth:`SplatRenderer._slope_constants`)."""

    normals: tuple
    constants: np.ndarray  # float32 (8,)
    sided: object | None = None


def _unseen_side(ops, x, y, zw, nx, ny, nz, sided, consts, unseen_cos):
    """Per point, whether the view sees the side of its surface the robot never saw: its side is
    known and the camera lies behind its oriented normal by more than ``unseen_cos`` (cosine
    between the normal and the ray towards the camera). The compiled front pass repeats it
    operation for operation in float32."""
    cx, cy, cz = (float(v) for v in consts[:3])
    dx, dy, dz = x - cx, y - cy, zw - cz
    d = nx * dx + ny * dy + nz * dz
    return (sided != 0) & (d > 0) & (d > float(np.float32(unseen_cos)) * ops.sqrt(dx * dx + dy * dy + dz * dz))


def _point_slope(ops, x, y, zw, zc, nx, ny, nz, consts):
    """Per point, how much its surface's camera depth changes per pixel (m / px): for the tangent
    plane n . X = d (camera frame), |grad z| = z^2 sqrt(nx^2 + ny^2) / (f |d|) = (z / f) * k with
    k = z sqrt(1 - (n . axis)^2) / |n . (P - C)|, capped at tan(max incidence). ``zc``: camera
    depth of the points. The compiled front pass repeats this expression operation for operation
    in float32, so both paths round alike."""
    cx, cy, cz, ax, ay, az, inv_f, inv_tan = (float(v) for v in consts)  # float32 values
    d = nx * (x - cx) + ny * (y - cy) + nz * (zw - cz)
    c = nx * ax + ny * ay + nz * az
    zs = zc * ops.sqrt(ops.clamp(1.0 - c * c, 0.0, None))
    den = ops.clamp(ops.maximum(ops.abs(d), zs * inv_tan), _MIN_PLANE_M, None)
    return zc * (zs / den) * inv_f


_MIN_PLANE_M = 1e-6  # float32 in both paths: a tangent plane through the camera still divides safely


@dataclass
class _Front:
    """The front layer of one view per padded pixel (flat, plus the miss bin at the end)."""

    n: int  # points rendered
    zbuf: object = None  # float32 minimum depth
    cnt: object = None  # float32 front-layer counts and sums
    s_z: object = None
    s_rgb: list | None = None
    s_u: object = None
    s_v: object = None
    s_sp: object = None  # sum of the front points' spacing (visibility mode only)
    best: object = None  # int64 nearest point id, -1 where none (labelled views only)
    s_g: object = None  # sum of the front points' depth slope (m / px; slope-scaled tolerance only)


def _images(ops, rgb, depth, hole, labels):
    """Backend images -> (rgb uint8 (H, W, 3), depth float32, hole bool, labels int32 or None)."""
    rgb_img = np.clip(np.rint(np.moveaxis(ops.to_numpy(rgb), 0, -1)), 0, 255).astype(np.uint8)
    return rgb_img, ops.to_numpy(depth).astype(np.float32), ops.to_numpy(hole), labels


def _empty(h: int, w: int):
    return (
        np.zeros((h, w, 3), np.uint8),
        np.zeros((h, w), np.float32),
        np.ones((h, w), bool),
        np.full((h, w), -1, np.int32),
    )


def _pinhole(camera: CameraIntrinsics | PinholeCamera | None) -> PinholeCamera:
    if camera is None:
        return PinholeCamera()
    if isinstance(camera, CameraIntrinsics):
        return camera.pinhole()
    return camera


RENDERERS: Registry[SplatRenderer] = Registry("renderer")


@RENDERERS.register("numpy", SplatConfig)
def _numpy_renderer(config: SplatConfig) -> SplatRenderer:
    return SplatRenderer(config, _NumpyOps())


@RENDERERS.register("torch", TorchSplatConfig)
def _torch_renderer(config: TorchSplatConfig) -> SplatRenderer:
    return SplatRenderer(config, _TorchOps(config.device))
