"""Exact occlusion culling of blocks for the ``visibility`` mode: a view skips the blocks that lie
wholly behind the surfaces around the camera, with images identical to drawing them.

Frustum culling and level of detail bound what a view draws by what lies in front of the camera,
not by what it can see: on an agent-built map ~80 % of the drawn points never reach a pixel's
front layer (far faces of walls, the rooms behind them), and in a three-storey building the
storeys above and below and every room within 20 m are drawn too (7x the points of a house).
This is two-pass hierarchical occlusion culling (Greene, Kass and Miller 1993, "Hierarchical
Z-buffer visibility"; the two-phase form of Hill and Collin 2011, "Practical, dynamic visibility
for games"): the blocks near the camera are projected first, their depths make an occluder image,
and every farther block whose screen rectangle lies behind that image is not drawn. Here the
occluder is not a z-buffer (a sampled surface leaves most pixels empty up close) but the same
quadrant covers the visibility test uses (:func:`visibility.enclosing_depth`): per pixel, the
farthest of the four nearest footprint depths around it.

Why skipping a block changes no pixel (the test below, per block ``b``). Let ``z_b`` be the
nearest camera depth of its bounding box and ``z' = (z_b - front_tol_m) / (1 + front_tol_rel)``:

* a surfel nearer than ``z'`` cannot take any of the block's points into its front layer, nor be
  displaced by them: it is unchanged;
* a surfel at ``z'`` or beyond (whether the block's points make, join or displace it) is removed
  by the visibility test in both images, when ``z' (1 - c T (1 + front_tol_rel) / f) - c T front_tol_m / f``
  exceeds ``C * (1 + tol_rel) + tol_m`` over the block's rectangle, ``C`` being the occluder's
  quadrant covers (``c T / f`` bounds the slope-scaled part of the tolerance:
  ``visibility_slope_px`` times the capped slope, ``tan(max incidence) / f`` per metre);
* such a surfel's footprint (radius at most ``footprint_scale * f * S / z'`` for the largest
  spacing ``S`` the view draws) stays inside the rectangle grown by that radius, where every cover
  is nearer than ``z'`` already: it changes no cover, so no enclosing depth, no fill;
* the largest footprint class, which decides which border quadrants are ignored, is unchanged
  when the block's classes lie below the largest class of the occluder's surfels.

The occluder is built only from surfels that no farther block can alter (nearer than
``(z_2 - front_tol_m) / (1 + front_tol_rel)``, ``z_2`` the nearest farther block) and with radii
from the smallest spacing of their points (no larger than the final footprint), so its covers
bound the final image's covers from above, in both images. Hence skipping the block leaves the
front layer of every visible surfel, every cover and every fill as they were: the images are
identical (tests/unit/renderer/test_renderer_occlusion.py compares them bit for bit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from shared.jit import AVAILABLE, kernel
from libs.pointrender import visibility
from libs.pointrender.kernels import _project_run

_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
# Occluder covers and the rectangle test run on tiles of this many pixels a side: the maximum
# over the tiles a rectangle touches bounds the maximum over the rectangle.
TILE_PX = 8


@dataclass(frozen=True)
class RunTable:
    """Per run of the drawn cloud (a block at one level of detail): its block and the largest
    spacing of its points; ``starts`` sorted, to find the run a view's slice begins at."""

    starts: np.ndarray  # int64
    block: np.ndarray  # int64
    max_spacing: np.ndarray  # float32


def run_table(starts: np.ndarray, counts: np.ndarray, spacing: np.ndarray, n_blocks: int) -> RunTable:
    """From the (levels, blocks) or (blocks,) starts and counts of the drawn cloud."""
    starts, counts = np.atleast_2d(starts).ravel(), np.atleast_2d(counts).ravel()
    block = np.tile(np.arange(n_blocks, dtype=np.int64), len(starts) // n_blocks)
    order = np.argsort(starts, kind="stable")
    starts, counts, block = starts[order], counts[order], block[order]
    nonzero = counts > 0
    starts, block = starts[nonzero].astype(np.int64), block[nonzero]
    # The non-empty runs partition the drawn cloud: one reduction over consecutive segments.
    max_sp = np.maximum.reduceat(spacing.astype(np.float32), starts) if len(starts) else np.zeros(0, np.float32)
    return RunTable(starts, block, max_sp.astype(np.float32))


@dataclass(frozen=True)
class OcclusionParams:
    near_m: float  # blocks nearer than this make the occluder
    min_points: int  # views drawing fewer points skip culling (the occluder costs ~1 ms)
    focal_px: float
    footprint_scale: float
    min_radius_px: int
    max_radius_px: int
    front_rel1: float  # 1 + front_tolerance_rel
    front_tol_m: float
    vis_rel1: float  # 1 + visibility_tolerance_rel
    vis_tol_m: float
    slope_per_m: float  # visibility_slope_px * tan(max incidence) / focal (0 without normals)
    near_clip_m: float
    far_clip_m: float


def cull(x, y, z, spacing, starts, counts, scale, table: RunTable, block_min, block_max,
         proj: np.ndarray, world_from_camera: np.ndarray, intrinsics: np.ndarray, h: int, w: int,
         lut: np.ndarray, p: OcclusionParams, pad: int = 1) -> np.ndarray:
    """Boolean mask of the runs ``starts, counts`` (scale: their spacing factor) a view must draw:
    False for those wholly behind the occluder of its near runs (module docstring). ``x, y, z,
    spacing``: the drawn cloud; ``proj``: float32 (3, 4) K [R^T | -R^T t] as the front pass
    uses it; ``lut``: :func:`visibility.radius_lut`; ``pad``: the pixels around the image the
    front pass projects into (its ring and guard band: the covers span them all)."""
    keep = np.ones(len(starts), bool)
    if len(starts) == 0 or int(counts.sum()) < p.min_points:
        return keep
    k = np.searchsorted(table.starts, starts, side="right") - 1
    blocks = table.block[k]
    max_sp = table.max_spacing[k] * scale
    # Each run's bounding box in the camera frame: nearest depth and screen rectangle.
    cam_from_world = np.linalg.inv(world_from_camera)
    lo, hi = block_min[blocks], block_max[blocks]
    corners = lo[:, None, :] + _CORNERS[None] * (hi - lo)[:, None, :]
    cc = corners @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    zc = cc[..., 2]
    z_b = zc.min(axis=1)
    phase1 = (z_b < p.near_m) | (counts == 0)
    far_runs = np.flatnonzero(~phase1 & (z_b < p.far_clip_m))
    if len(far_runs) == 0 or not phase1.any():
        return keep
    z2 = float(z_b[~phase1].min())
    z_safe = (z2 - p.front_tol_m) / p.front_rel1
    zbuf, spmin = occluder_depths(x, y, z, spacing, starts[phase1], counts[phase1], scale[phase1], proj.ravel(),
                                  np.float32(p.near_clip_m), np.float32(p.far_clip_m), w, h, pad)
    tiles, reach = occluder_tiles(zbuf, spmin, z_safe, h + 2 * (pad - 1), w + 2 * (pad - 1), lut, p)
    if reach < 0:
        return keep
    # Screen rectangles (padded pixel coordinates) of the farther runs (a box wholly in front of
    # the camera projects inside the hull of its corners), grown by the largest footprint class
    # any surfel they can alter may have, plus a pixel for rounding.
    uv = cc[far_runs] @ np.asarray(intrinsics, np.float64).T
    u, v = uv[..., 0] / uv[..., 2], uv[..., 1] / uv[..., 2]
    zp = (z_b[far_runs] - p.front_tol_m) / p.front_rel1
    s_view = float(max_sp.max())
    r_exp = np.clip(np.ceil(p.footprint_scale * p.focal_px * s_view / zp - 0.5), p.min_radius_px, p.max_radius_px)
    r_cls = lut[(r_exp + 1).astype(np.int64)].astype(np.int64)
    grow = r_cls + 2  # + the padding ring and rounding of u, v to pixels
    col0 = np.floor(u.min(axis=1) + 0.5).astype(np.int64) + pad - grow
    col1 = np.floor(u.max(axis=1) + 0.5).astype(np.int64) + pad + grow
    row0 = np.floor(v.min(axis=1) + 0.5).astype(np.int64) + pad - grow
    row1 = np.floor(v.max(axis=1) + 0.5).astype(np.int64) + pad + grow
    ahead = (zc[far_runs] > p.near_clip_m).all(axis=1)
    # The depth a surfel at z' or beyond exceeds its enclosing depth's tolerance by, at least.
    margin = zp * (1.0 - p.slope_per_m * p.front_rel1) - p.slope_per_m * p.front_tol_m
    hidden = cull_test(tiles, TILE_PX, row0, row1, col0, col1, margin, r_cls, ahead, reach, h + 2 * pad, w + 2 * pad,
                       np.float32(p.vis_rel1), np.float32(p.vis_tol_m))
    keep[far_runs[hidden]] = False
    return keep


def _occluder_depths(x, y, z, spacing, starts, counts, scale, proj, near, far, w, h, pad):
    """Per pixel of the image padded by ``pad`` (plus the spare bin): the nearest depth of the
    runs' points and the smallest spacing among them, projected exactly as the front pass
    projects them."""
    npad = (h + 2 * pad) * (w + 2 * pad)
    zbuf = np.empty(npad + 1, np.float32)  # np.empty and fills, not np.full: see kernels._front_pass
    zbuf[:] = np.inf
    spmin = np.empty(npad + 1, np.float32)
    spmin[:] = np.inf
    m_max = 0
    for r in range(counts.shape[0]):
        m_max = max(m_max, counts[r])
    q_of = np.empty(m_max, np.int32)
    z_of = np.empty(m_max, np.float32)
    uv_of = np.empty(1, np.int32)
    for r in range(counts.shape[0]):
        s, m, sc = starts[r], counts[r], scale[r]
        # np.bool_(False), not the constant False: numba would compile _project_run again for a constant
        # argument (Literal[bool]) beside the front pass's runtime flag, for the same code.
        _project_run(x[s : s + m], y[s : s + m], z[s : s + m], proj, near, far, w, h, q_of[:m], z_of[:m], uv_of,
                     np.bool_(False), pad)
        for i in range(m):
            q = q_of[i]
            zbuf[q] = min(zbuf[q], z_of[i])
            spmin[q] = min(spmin[q], spacing[s + i] * sc)
    return zbuf, spmin


def occluder_tiles(zbuf, spmin, z_safe: float, h: int, w: int, lut: np.ndarray, p: OcclusionParams):
    """Tile maxima of the occluder's per-pixel cover depth C (the farthest of the four quadrant
    covers, +inf where one is empty) and the largest footprint class among its surfels (-1: none)."""
    hp, wp = h + 2, w + 2
    zimg = zbuf[: hp * wp].reshape(hp, wp)
    simg = spmin[: hp * wp].reshape(hp, wp)
    f32 = np.float32
    # int8 as the visibility pass's classes (-1..max_radius_px <= 64): visibility_kernels.bucket then
    # has one signature for both, not a second compile (0.2-0.4 s of CPU on a cold cache).
    cls = np.empty((hp, wp), np.int8)
    hist = np.zeros(p.max_radius_px + 1, np.int64)
    occluder_classes(zimg, simg, f32(z_safe), f32(p.footprint_scale * p.focal_px), f32(p.min_radius_px),
                     f32(p.max_radius_px), lut, cls, hist)
    present = [int(k) for k in np.flatnonzero(hist)]
    if not present:
        return None, -1
    from libs.pointrender import visibility_kernels as vk

    order, first = vk.bucket(cls, hist)
    cov4 = np.full((hp, wp, 4), np.inf, f32)
    border = (float("inf"),) * 4
    for i, k in enumerate(reversed(present)):
        vk.add_sources(cov4, order, first[k], first[k + 1], zimg)
        nxt = present[-2 - i] if i + 1 < len(present) else 0
        if k > nxt:
            m = k - nxt
            cov4 = cv2.erode(cov4, np.ones((m + 1, m + 1), np.uint8), anchor=(m, m),
                             borderType=cv2.BORDER_CONSTANT, borderValue=border)
    th, tw = -(-hp // TILE_PX), -(-wp // TILE_PX)
    tiles = np.empty((th, tw), f32)
    cover_tiles(cov4, tiles, TILE_PX)
    return tiles, present[-1]


def _occluder_classes(zimg, simg, z_safe, fs_focal, rmin, rmax, lut, cls, hist):
    """Footprint class of each occluder surfel (nearer than ``z_safe``), -1 elsewhere: the radius
    from the smallest spacing in the pixel, no larger than the radius the final image gives it."""
    hp, wp = zimg.shape
    half = np.float32(0.5)
    one = np.float32(1.0)
    shrink = np.float32(1.0 - 1e-5)
    for i in range(hp):
        for j in range(wp):
            zv = zimg[i, j]
            if zv < z_safe:
                # Slightly below the smallest spacing: the final image's mean spacing, rounded to
                # float32, is never below it.
                rad = np.ceil(simg[i, j] * shrink * fs_focal / zv - half)
                rad = min(max(rad, rmin), rmax)
                k = np.int32(lut[np.int64(rad + one)])
                cls[i, j] = k
                hist[k] += 1
            else:
                cls[i, j] = -1


def _cover_tiles(cov4, tiles, tile):
    """Per tile: the largest, over its pixels, of the farthest quadrant cover (+inf where empty)."""
    hp, wp, _ = cov4.shape
    th, tw = tiles.shape
    for ti in range(th):
        for tj in range(tw):
            m = np.float32(-np.inf)
            for i in range(ti * tile, min((ti + 1) * tile, hp)):
                ii = hp - 1 - i
                for j in range(tj * tile, min((tj + 1) * tile, wp)):
                    jj = wp - 1 - j
                    m = max(m, max(max(cov4[i, j, 0], cov4[i, jj, 1]), max(cov4[ii, j, 2], cov4[ii, jj, 3])))
            tiles[ti, tj] = m


def _cull_test(tiles, tile, row0, row1, col0, col1, margin, r_cls, ahead, reach, hp, wp, vis_rel1, vis_tol):
    """Per run: True when its grown rectangle lies behind the occluder (see the module docstring)."""
    n = row0.shape[0]
    out = np.empty(n, np.bool_)  # not np.zeros: see kernels._front_pass
    out[:] = False
    th, tw = tiles.shape
    for r in range(n):
        if not ahead[r] or r_cls[r] >= reach:
            continue
        a, b = max(row0[r], 0), min(row1[r], hp - 1)
        c, d = max(col0[r], 0), min(col1[r], wp - 1)
        if a > b or c > d:  # wholly off the padded image: none of its points lands on a pixel
            out[r] = True
            continue
        m = np.float32(-np.inf)
        for ti in range(a // tile, b // tile + 1):
            for tj in range(c // tile, d // tile + 1):
                m = max(m, tiles[ti, tj])
        out[r] = margin[r] > m * vis_rel1 + vis_tol
    return out


if AVAILABLE:
    _jit = kernel(error_model="numpy")
    occluder_depths, occluder_classes = _jit(_occluder_depths), _jit(_occluder_classes)
    cover_tiles, cull_test = _jit(_cover_tiles), _jit(_cull_test)
else:  # pragma: no cover - the renderer culls only on the compiled path
    occluder_depths = occluder_classes = cover_tiles = cull_test = None
