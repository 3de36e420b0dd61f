"""Occlusion-correct, hole-free anticipated views: the image-space half of the ``visibility`` mode.

The splat's front pass (:mod:`splat`, :mod:`kernels`) leaves one surfel per pixel: the points of
that pixel within a depth tolerance of its nearest one (count, mean depth, mean colour, the nearest
point's label, the mean *spacing* of those points on their surface). A sparse or near surface
leaves gaps between its surfels, and the fixed 3x3 splat of the paper lets the room behind a wall
show through them. This module follows the two screen-space passes of **visibility splatting**
with **pull-push hole filling**:

1. *Visibility* (Pfister et al. 2000, "Surfels", sec. 5.2; the hierarchical form of Rosenthal and
   Linsen 2008, "Image-space point cloud rendering"): every surfel covers a disk whose radius in
   pixels follows its points' local spacing and its depth, ``r = footprint_scale * f * spacing / z``
   (so a wall 0.5 m away gets wide footprints, a far wall narrow ones). The nearest depth of the
   footprints that cover each pixel (the coverage depth) is computed as a min-dilation with a
   radius per source, done in ``max_radius_px`` exact 3x3 min-filter steps: the sources of radius
   ``k`` enter at step ``max - k`` and grow by one pixel per step (square and cross kernels
   alternate, so the footprint is an octagon close to the disk). A surfel farther than the depth
   tolerance behind the coverage depth of its own pixel is background seen through a gap and is
   removed.
2. *Hole filling* (pull-push, Marroquim, Kraus and Cavalcanti 2007, "Efficient point-based
   rendering using image reconstruction"; Grossman and Dally 1998): the visible surfels are pulled
   into an image pyramid in which each coarse cell averages only the children in the front depth
   band of that cell, so a coarse cell never mixes a foreground with the background. A pixel
   covered by a footprint but without a visible surfel of its own takes the value of the finest
   ancestor cell whose depth agrees with the pixel's coverage depth; a pixel that no footprint
   covers is filled only from an ancestor cell (at most ``gap_levels`` up) whose whole depth range
   lies within the tolerance (one surface) and whose width on that surface is at most
   ``gap_max_m``, so no surface is invented across a depth edge or over an unmapped stretch. Depth
   and labels follow the same choice as colour: the label of a filled pixel is the label of the
   nearest surfel of the accepted cell.

Everything here is array code over one small ops interface (numpy with OpenCV's exact min
filters, or torch), whose results agree exactly except for float32 rounding in the per-pixel
division of two sums; the tests bound the difference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FrontLayer:
    """Per padded pixel ((H + 2) x (W + 2)): the front-layer surfel the splat's front pass left."""

    zmin: object  # float32, inf where no point
    count: object  # float32
    sum_z: object  # float32
    sum_rgb: list  # three float32 images
    sum_spacing: object | None  # float32, sum of the front points' spacing (m), LOD-scaled
    label: object | None  # int64, the nearest point's label, -1 where none


@dataclass(frozen=True)
class VisibilityParams:
    focal_px: float
    footprint_scale: float
    max_radius_px: int
    min_radius_px: int
    gap_levels: int
    gap_max_m: float
    fill_levels: int
    tol_rel1: float  # 1 + relative depth tolerance
    tol_abs_m: float


def compose(ops, front: FrontLayer, p: VisibilityParams, h: int, w: int):
    """The view (rgb (3, H, W) float, depth (H, W), hole (H, W) bool, labels (H, W) int64 or None)."""
    levels = max(p.fill_levels, p.gap_levels)
    cell = 1 << levels
    hp, wp = h + 2, w + 2
    # The pyramid halves each level: pad the grid to a multiple of its coarsest cell.
    hq, wq = -(-hp // cell) * cell, -(-wp // cell) * cell
    inf = float("inf")

    def pad(a, value):
        return ops.pad2(a, hq - hp, wq - wp, value)

    zmin = pad(front.zmin, inf)
    has = zmin < inf
    count = ops.where(has, pad(front.count, 0.0), 1.0)
    zmean = pad(front.sum_z, 0.0) / count
    rgb = [pad(c, 0.0) / count for c in front.sum_rgb]
    label = None if front.label is None else pad(front.label, -1)

    # 1. Visibility: the coverage depth from per-source footprints, then the test against it.
    spacing = pad(front.sum_spacing, 0.0) / count
    radius = ops.clamp(ops.floor(spacing * (p.footprint_scale * p.focal_px) / ops.where(has, zmin, 1.0) + 0.5),
                       float(p.min_radius_px), float(p.max_radius_px))
    radius = ops.where(has, radius, -1.0)
    top = int(ops.max_value(radius)) if bool(ops.any(has)) else -1
    cover = ops.full2(hq, wq, inf)
    for k in range(top, 0, -1):
        cover = ops.minimum(cover, ops.where(radius == float(k), zmin, inf))
        cover = ops.erode3(cover, cross=(k % 2 == 0))
    cover = ops.minimum(cover, ops.where(radius == 0.0, zmin, inf))
    visible = has & (zmin <= cover * p.tol_rel1 + p.tol_abs_m)

    # 2. Pull: the pyramid of visible surfels, each cell averaging its front-band children.
    weight = ops.as_f32(visible)
    pyr = [_Level(weight, zmean * weight, [c * weight for c in rgb], ops.where(visible, zmean, inf),
                  ops.where(visible, zmean, -inf), None if label is None else ops.where(visible, label, -1))]
    for _ in range(levels):
        pyr.append(_pull(ops, pyr[-1], p))

    # Push: each pixel without a visible surfel takes its finest acceptable ancestor.
    out_z = ops.where(visible, zmean, 0.0)
    out_rgb = [ops.where(visible, c, 0.0) for c in rgb]
    out_lab = None if label is None else ops.where(visible, label, -1)
    done = visible
    covered = cover < inf
    ref = ops.where(covered, cover, 0.0)
    tol_rel = p.tol_rel1 - 1.0
    for lev in range(1, levels + 1):
        q = pyr[lev]
        s = 1 << lev
        wgt = ops.up(q.weight, s)
        safe = ops.where(wgt > 0, wgt, 1.0)
        mz = ops.up(q.sum_z, s) / safe
        take = None
        if lev <= p.fill_levels:  # covered by a footprint: the ancestor must agree with the coverage depth
            take = covered & (wgt > 0) & (ops.abs(mz - ref) <= ref * tol_rel + p.tol_abs_m)
        if lev <= p.gap_levels:  # a gap no footprint covers: only inside one surface
            lo, hi = ops.up(q.zlo, s), ops.up(q.zhi, s)
            gap = ~covered & (wgt > 0) & (hi - lo <= lo * tol_rel + p.tol_abs_m)
            gap = gap & (lo * (s / p.focal_px) <= p.gap_max_m)
            take = gap if take is None else take | gap
        take = take & ~done
        out_z = ops.where(take, mz, out_z)
        out_rgb = [ops.where(take, ops.up(c, s) / safe, o) for c, o in zip(q.sum_rgb, out_rgb)]
        if out_lab is not None:
            out_lab = ops.where(take, ops.up(q.label, s), out_lab)
        done = done | take

    crop = (slice(1, 1 + h), slice(1, 1 + w))
    hole = ~done[crop]
    rgb_img = ops.stack([c[crop] for c in out_rgb])
    return rgb_img, out_z[crop], hole, None if out_lab is None else out_lab[crop]


@dataclass
class _Level:
    weight: object
    sum_z: object
    sum_rgb: list
    zlo: object  # nearest surfel depth in the cell (inf: none)
    zhi: object  # farthest kept surfel depth (-inf: none)
    label: object | None  # label of the nearest kept child


_CHILDREN = ((0, 0), (0, 1), (1, 0), (1, 1))


def _pull(ops, lev: _Level, p: VisibilityParams) -> _Level:
    """One coarser level: each cell keeps the children within the depth tolerance of its nearest
    child (by mean depth), summed in a fixed order so that every backend rounds alike."""
    inf = float("inf")

    def child(a, dy, dx):
        return a[dy::2, dx::2]

    means = []
    for dy, dx in _CHILDREN:
        wgt = child(lev.weight, dy, dx)
        means.append(ops.where(wgt > 0, child(lev.sum_z, dy, dx) / ops.where(wgt > 0, wgt, 1.0), inf))
    front = means[0]
    for m in means[1:]:
        front = ops.minimum(front, m)
    thr = front * p.tol_rel1 + p.tol_abs_m
    weight = sum_z = zlo = zhi = label = assigned = None
    sum_rgb = [None, None, None]
    for (dy, dx), m in zip(_CHILDREN, means):
        keep = m <= thr
        k = ops.as_f32(keep)
        cw, cz = child(lev.weight, dy, dx) * k, child(lev.sum_z, dy, dx) * k
        c_lo = ops.where(keep, child(lev.zlo, dy, dx), inf)
        c_hi = ops.where(keep, child(lev.zhi, dy, dx), -inf)
        c_rgb = [child(c, dy, dx) * k for c in lev.sum_rgb]
        # The label of the nearest child (the first one in the fixed order on ties).
        nearest = keep & (m == front)
        if weight is None:
            weight, sum_z, zlo, zhi, sum_rgb = cw, cz, c_lo, c_hi, c_rgb
            if lev.label is not None:
                label, assigned = ops.where(nearest, child(lev.label, dy, dx), -1), nearest
        else:
            weight, sum_z = weight + cw, sum_z + cz
            zlo, zhi = ops.minimum(zlo, c_lo), ops.maximum(zhi, c_hi)
            sum_rgb = [a + c for a, c in zip(sum_rgb, c_rgb)]
            if lev.label is not None:
                label = ops.where(nearest & ~assigned, child(lev.label, dy, dx), label)
                assigned = assigned | nearest
    return _Level(weight, sum_z, sum_rgb, zlo, zhi, label)


def point_spacing(xyz: np.ndarray, neighbours: int = 4, lo_m: float = 0.002, hi_m: float = 0.1) -> np.ndarray:
    """Local point spacing per point (float32, metres): the mean distance to its ``neighbours``
    nearest points, between ``lo_m`` and ``hi_m`` (an isolated outlier does not get a huge disk)."""
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(xyz).query(xyz, k=neighbours + 1, workers=-1)
    return np.clip(dist[:, 1:].mean(axis=1), lo_m, hi_m).astype(np.float32)
