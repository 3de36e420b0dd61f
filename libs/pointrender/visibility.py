"""Occlusion-correct, hole-free anticipated views: the image-space half of the ``visibility`` mode.

The splat's front pass (:mod:`splat`, :mod:`kernels`) leaves one surfel per pixel: the points of
that pixel within a depth tolerance of its nearest one (count, mean depth, mean colour, the nearest
point's label, the mean *spacing* of those points on their surface). A sparse or near surface
leaves gaps between its surfels, and the fixed 3x3 splat of the paper lets the room behind a wall
show through them. This module follows the two screen-space passes of **visibility splatting**
with **pull-push hole filling**:

1. *Visibility* (visibility splatting, Pfister et al. 2000, "Surfels", sec. 5.2, in image space
   as in Rosenthal and Linsen 2008, "Image-space point cloud rendering", with the sector test of
   Pintus, Gobbetti and Agus 2011, "Real-time rendering of massive unstructured raw point clouds
   using screen-space operators"): every surfel covers a square whose half-width in pixels
   follows its points' local spacing and its depth, ``r = footprint_scale * f * spacing / z``
   (a wall 0.5 m away gets wide footprints, a far wall narrow ones). Per pixel and per quadrant
   of its neighbourhood the nearest depth of the footprints reaching it from that quadrant is a
   min-dilation with a radius per source (radii rounded up to a few classes, exact min filters
   with the window on the quadrant's side); the farthest of the four quadrant depths is the
   surface that *encloses* the pixel. A surfel behind that surface (by more than the depth
   tolerance) is background seen through a gap and is removed. The tolerance is a slope-scaled
   depth bias (as OpenGL's polygon offset, ``factor * slope + units``): a few centimetres plus
   ``slope_px`` pixels' worth of the surfel's own surface's depth change per pixel, known from the
   map's normals (:func:`point_normals`). A wall seen face-on thus gets ~2-3 cm, less than the
   10 cm between the two faces of a wall between rooms, whose far face no longer fills the near
   face's sampling gaps; a wall seen at a grazing angle gets the depth it spans across a pixel,
   so its nearer surfels do not remove its farther ones. Requiring all four quadrants
   is what keeps two things right that a centred footprint gets wrong: a plane never encloses
   its own farther pixels (the quadrant up its depth gradient holds no nearer point), so a wall
   seen along a corridor is not its own occluder; and a background surfel just outside a
   foreground silhouette keeps its place, so footprints do not grow objects (nor their labels).
   The footprints include those of the points just outside the image (a guard band, as
   screen-space passes render one): otherwise a pixel near the border has only the few columns
   between it and the edge on that side, and the room behind a near wall passes there.
2. *Hole filling* (pull-push, Marroquim, Kraus and Cavalcanti 2007, "Efficient point-based
   rendering using image reconstruction"; Grossman and Dally 1998): the visible surfels are pulled
   into an image pyramid in which each coarse cell averages only the children in the front depth
   band of that cell, so a coarse cell never mixes a foreground with the background. A pixel
   enclosed by footprints but without a visible surfel of its own takes the value of the finest
   ancestor cell whose depth lies between the second-nearest and the farthest quadrant depth of
   the pixel (with a slope allowance that grows with the cell); a pixel not enclosed on every
   side is filled only from an ancestor cell (at most ``gap_levels`` up) whose whole depth range
   lies within the tolerance (one surface) and whose width on that surface is at most
   ``gap_max_m``, so no surface is invented across a depth edge or over an unmapped stretch. Depth
   and labels follow the same choice as colour: the label of a filled pixel is the label of the
   nearest surfel of the accepted cell.

Everything here is array code over one small ops interface (numpy with OpenCV's exact min
filters, or torch), whose results agree exactly except for float32 rounding in the per-pixel
division of two sums; the tests bound the difference.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from shared.geometry import pca_normals

# The quadrant covers' depth codes live with the compiled loops' shared constants (no import circle).
from .cover_codes import COVER_MAX_CODE, COVER_NONE


@dataclass
class FrontLayer:
    """Per pixel of the image padded by its 1-pixel ring and ``VisibilityParams.guard_px`` more on
    every side ((H + 2 + 2g) x (W + 2 + 2g)): the front-layer surfel the splat's front pass left.
    The guard band's surfels only count as footprints of the visibility test."""

    zmin: object  # float32, inf where no point
    count: object  # float32
    sum_z: object  # float32
    sum_rgb: list  # three float32 images
    sum_spacing: object | None  # float32, sum of the front points' spacing (m), LOD-scaled
    label: object | None  # int64, the nearest point's label, -1 where none
    # float32, sum of the front points' depth slope (m per px of their surface), or None
    sum_slope: object | None = None


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
    # Relative depth change per pixel of a surface seen at the steepest slope the filling allows
    # (tan(slope) / focal): a filled pixel's tolerance grows by this much per pixel of cell width.
    slope_per_px: float = 0.0
    # Colour reconstruction filter: each pixel's colour is blended with its 3x3 neighbours
    # (binomial weights) whose depth lies within this fraction of its own (0: off).
    filter_rel: float = 0.0
    # Slope-scaled tolerance of the visibility test: a surfel may lie this many pixels' worth of
    # its own surface's depth slope (``FrontLayer.sum_slope``) behind the enclosing surface.
    slope_px: float = 0.0
    # Width of the band around the padded image (pixels) whose surfels the front layer holds as
    # footprints only (:class:`splat.SplatConfig` ``guard_px`` says why).
    guard_px: int = 0
    # The quadrant covers hold depths as codes ceil(depth / depth_step_m) below COVER_NONE (see
    # there): the renderer sets the step to its far clip / COVER_MAX_CODE.
    depth_step_m: float = 20.0 / COVER_MAX_CODE


def compose(ops, front: FrontLayer, p: VisibilityParams, h: int, w: int):
    """The view (rgb (3, H, W) float, depth (H, W), hole (H, W) bool, labels (H, W) int64 or None)."""
    levels = max(p.fill_levels, p.gap_levels)
    hp, wp = h + 2, w + 2
    hq, wq, oy, ox = pyramid_grid(h, w, levels)
    inf = float("inf")
    g = p.guard_px
    inner = (slice(g, g + hp), slice(g, g + wp))

    def pad(a, value):  # the padded image (without the guard band), centred in the pyramid's grid
        return ops.pad2(a[inner], oy, hq - hp - oy, ox, wq - wp - ox, value)

    # 1. Visibility: the enclosing depth of each pixel from per-source footprints (those of the
    # guard band included), then the test of each surfel against the enclosing depth of its own pixel.
    has_g = front.zmin < inf
    count_g = ops.where(has_g, front.count, 1.0)
    spacing = front.sum_spacing / count_g
    radius = ops.ceil(spacing * (p.footprint_scale * p.focal_px) / ops.where(has_g, front.zmin, 1.0) - 0.5)
    radius = ops.where(has_g, ops.clamp(radius, float(p.min_radius_px), float(p.max_radius_px)), -1.0)
    far, near2 = enclosing_depth(ops, front.zmin, radius, p, h + 2 * g, w + 2 * g)
    far, near2 = pad(far, inf), pad(near2, inf)

    zmin = pad(front.zmin, inf)
    has = zmin < inf
    count = ops.where(has, pad(front.count, 0.0), 1.0)
    zmean = pad(front.sum_z, 0.0) / count
    rgb = [pad(c, 0.0) / count for c in front.sum_rgb]
    label = None if front.label is None else pad(front.label, -1)
    limit = far * p.tol_rel1 + p.tol_abs_m
    if front.sum_slope is not None:
        limit = limit + pad(front.sum_slope, 0.0) / count * p.slope_px
    visible = has & (zmin <= limit)

    # 2. Pull: the pyramid of visible surfels, each cell averaging its front-band children.
    weight = ops.as_f32(visible)
    pyr = [_Level(weight, zmean * weight, [c * weight for c in rgb], ops.where(visible, zmean, inf),
                  ops.where(visible, zmean, -inf), None if label is None else ops.where(visible, label, -1))]
    for _ in range(levels):
        pyr.append(_pull(ops, pyr[-1], p))

    # Push: each pixel without a visible surfel takes its finest acceptable ancestor. Only the
    # pixels still open are visited (few, on a good map).
    out_z = ops.where(visible, zmean, 0.0)
    out_rgb = [ops.where(visible, c, 0.0) for c in rgb]
    out_lab = None if label is None else ops.where(visible, label, -1)
    done = visible
    crop = crop_of(h, w, oy, ox)
    rows, cols = ops.nonzero2(~visible[crop])
    rows, cols = rows + 1 + oy, cols + 1 + ox  # pyramid coordinates
    ref, ref_lo = far[rows, cols], near2[rows, cols]
    covered = ref < inf
    tol_rel = p.tol_rel1 - 1.0
    for lev in range(1, levels + 1):
        if rows.shape[0] == 0:
            break
        q = pyr[lev]
        pr, pc = rows >> lev, cols >> lev
        wgt = q.weight[pr, pc]
        safe = ops.where(wgt > 0, wgt, 1.0)
        mz = q.sum_z[pr, pc] / safe
        take = None
        # A sloped surface changes depth across a cell: the tolerance grows with the cell's width
        # (half of it from the pixel to the cell's mean, all of it across the cell).
        half_slope = p.slope_per_px * min(1 << (lev - 1), SLOPE_CELL_PX)
        full_slope = p.slope_per_px * min(1 << lev, SLOPE_CELL_PX)
        if lev <= p.fill_levels:  # enclosed: the ancestor lies between the enclosing depths
            rel = tol_rel + half_slope
            take = covered & (wgt > 0) & (mz <= ref * (1.0 + rel) + p.tol_abs_m)
            take = take & (mz >= ref_lo * (1.0 - rel) - p.tol_abs_m)
        if lev <= p.gap_levels:  # a gap footprints do not enclose: only inside one surface, and a narrow one
            lo, hi = q.zlo[pr, pc], q.zhi[pr, pc]
            gap = ~covered & (wgt > 0) & (hi - lo <= lo * (tol_rel + full_slope) + p.tol_abs_m)
            gap = gap & (lo * ((1 << lev) / p.focal_px) <= p.gap_max_m)
            take = gap if take is None else take | gap
        if take is None:
            break
        r, c = rows[take], cols[take]
        out_z[r, c] = mz[take]
        for o, sc in zip(out_rgb, q.sum_rgb):
            o[r, c] = sc[pr[take], pc[take]] / safe[take]
        if out_lab is not None:
            out_lab[r, c] = q.label[pr[take], pc[take]]
        done[r, c] = True
        keep = ~take
        rows, cols, ref, ref_lo, covered = rows[keep], cols[keep], ref[keep], ref_lo[keep], covered[keep]

    hole = ~done[crop]
    rgb_img = ops.stack([c[crop] for c in out_rgb])
    if p.filter_rel > 0:
        rgb_img = colour_filter(ops, rgb_img, out_z[crop], hole, p.filter_rel)
    return rgb_img, out_z[crop], hole, None if out_lab is None else out_lab[crop]


# The 3x3 binomial kernel ([1 2 1] / 4 in each direction), in the fixed order every backend sums.
FILTER_TAPS = tuple((dy, dx, (2 - abs(dy)) * (2 - abs(dx)) / 16.0) for dy in (-1, 0, 1) for dx in (-1, 0, 1))


def colour_filter(ops, rgb, depth, hole, rel: float):
    """The image-space reconstruction filter of surface splatting (Zwicker, Pfister, van Baar and
    Gross 2001, "Surface splatting": overlapping splats of one surface are blended, not
    painted over; here the blend is a 3x3 binomial over the finished pixels): a pixel's colour
    becomes the weighted mean of its neighbours on the same surface, those whose depth lies
    within ``rel`` of its own. One sample per pixel from a map sampled at about the pixel pitch
    is noisy; the blend removes that noise without crossing a depth edge. Depth, labels and
    holes are unchanged."""
    h, w = depth.shape
    inf = float("inf")
    dpad = ops.pad_ring(ops.where(hole, inf, depth), inf)
    rpad = [ops.pad_ring(c, 0.0) for c in (rgb[0], rgb[1], rgb[2])]
    tol = depth * rel
    acc = [None, None, None]
    wsum = None
    for dy, dx, k in FILTER_TAPS:
        ds = dpad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        wt = ops.as_f32(ops.abs(ds - depth) <= tol) * k
        wsum = wt if wsum is None else wsum + wt
        for c in range(3):
            term = rpad[c][1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] * wt
            acc[c] = term if acc[c] is None else acc[c] + term
    safe = ops.where(wsum > 0, wsum, 1.0)
    return ops.stack([ops.where(hole, 0.0, a / safe) for a in acc])


# Footprint radii (px) are rounded up to these classes (plus the configured maximum).
RADIUS_CLASSES = (0, 1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48)
# The slope allowance of the hole filling stops growing past cells this wide (px): a coarse cell's
# mean is a fill value only where the surface is nearly flat across it anyway.
SLOPE_CELL_PX = 4

# The four quadrants of a pixel's neighbourhood, as the side (rows, columns) on which their
# sources lie: -1 above / left, +1 below / right (the pixel's own row and column in both).
QUADRANTS = ((-1, -1), (-1, 1), (1, -1), (1, 1))


def radius_lut(p: VisibilityParams) -> np.ndarray:
    """float32 table: footprint radius + 1 -> its class (-1: no source)."""
    classes = [k for k in RADIUS_CLASSES if p.min_radius_px <= k < p.max_radius_px] + [p.max_radius_px]
    lut = np.full(p.max_radius_px + 2, -1.0, np.float32)
    for r in range(p.max_radius_px, -1, -1):
        lut[r + 1] = min(k for k in classes if k >= r)
    return lut


def enclosing_depth(ops, zmin, radius, p: VisibilityParams, h: int, w: int):
    """Per pixel, from the footprints that reach it: ``(far, near2)``, the farthest and the
    second-nearest of its four quadrant depths (each the nearest depth of a footprint reaching the
    pixel from that quadrant); ``far`` is inf where some quadrant holds no footprint.

    ``far`` is the depth of the nearest surface that encloses the pixel on every side: a surfel
    behind it is seen through a gap of that surface. A plane never encloses its own farther
    pixels (the quadrant up its depth gradient holds no nearer point), so an oblique wall is not
    its own occluder, and a background pixel just outside a foreground silhouette keeps its own
    surfel (the quadrants away from the silhouette see the background): footprints do not grow
    objects. The depth of a filled pixel must lie between ``near2`` and ``far``.

    ``zmin`` and ``radius`` span the image of ``h`` x ``w`` padded by one pixel (and by any rows
    and columns of +inf / -1 on the bottom and right). A quadrant whose window leaves that image
    and holds no footprint is not counted: the surface may continue beyond the border (what the
    renderer's guard band makes rare: the image here is the view grown by it). Radii are rounded up to a few classes so that the dilation
    costs a handful of exact min filters (O(1) per pixel whatever the size); the sources of class
    k join at the step after which k pixels of dilation remain. Depths enter the covers as codes
    (:data:`COVER_NONE`), so ``far`` and ``near2`` are multiples of ``p.depth_step_m``."""
    inf = float("inf")
    hq, wq = zmin.shape
    cls = ops.lookup(radius_lut(p), radius + 1.0)
    present = sorted(int(k) for k in ops.unique_values(cls) if k >= 0)
    if not present:
        return ops.full2(hq, wq, inf), ops.full2(hq, wq, inf)
    code = ops.where(zmin < inf, ops.clamp(ops.ceil(zmin * (1.0 / p.depth_step_m)), 0.0, float(COVER_MAX_CODE)), inf)
    covers = [ops.full2(hq, wq, inf) for _ in QUADRANTS]
    for i, k in enumerate(reversed(present)):
        src = ops.where(cls == float(k), code, inf)
        covers = [ops.minimum(c, src) for c in covers]
        nxt = present[-2 - i] if i + 1 < len(present) else 0
        if k > nxt:
            covers = [ops.erode_quadrant(c, k - nxt, sy, sx) for c, (sy, sx) in zip(covers, QUADRANTS)]
    # Quadrants that reach past the image (within the largest radius of its border) and found
    # nothing do not count; the pixel's other quadrants decide.
    reach = present[-1]
    rows = ops.index_grid(hq, wq, 0)
    cols = ops.index_grid(hq, wq, 1)
    hi, lo = [], []
    for c, (sy, sx) in zip(covers, QUADRANTS):
        out_r = rows <= reach if sy < 0 else rows >= h + 1 - reach
        out_c = cols <= reach if sx < 0 else cols >= w + 1 - reach
        ignored = (c == inf) & (out_r | out_c)
        hi.append(ops.where(ignored, -inf, c))
        lo.append(c)  # an ignored quadrant is inf already: it never is the nearest
    far = ops.maximum(ops.maximum(hi[0], hi[1]), ops.maximum(hi[2], hi[3]))
    far = ops.where(far == -inf, inf, far)
    # The second smallest of four: the smaller of (larger of the pair minima, smaller of the pair maxima).
    near2 = ops.minimum(ops.maximum(ops.minimum(lo[0], lo[1]), ops.minimum(lo[2], lo[3])),
                        ops.minimum(ops.maximum(lo[0], lo[1]), ops.maximum(lo[2], lo[3])))
    far, near2 = (ops.where(c < inf, c * p.depth_step_m, inf) for c in (far, near2))  # codes -> metres
    return far, ops.minimum(near2, far)


def crop_of(h: int, w: int, oy: int = 0, ox: int = 0):
    """The image inside the padded grid placed at (``oy``, ``ox``) of the pyramid's grid."""
    return slice(1 + oy, 1 + oy + h), slice(1 + ox, 1 + ox + w)


def pyramid_grid(h: int, w: int, levels: int) -> tuple[int, int, int, int]:
    """``(hq, wq, oy, ox)``: the pull-push pyramid's grid (the padded image's (h + 2) x (w + 2)
    rounded up to a multiple of its coarsest cell, 2^levels) and where the padded image sits in
    it: centred, so that no image border falls at the start of a coarse cell with nothing of the
    image beyond it. (At the corner, (256 + 2) rows in a grid of 288 put the last image row alone
    with the ring below it in every cell up to 32 px: a pixel there whose own surfel the
    visibility test removed had no ancestor to fill from but the ring, and stayed a hole.)"""
    cell = 1 << levels
    hp, wp = h + 2, w + 2
    hq, wq = -(-hp // cell) * cell, -(-wp // cell) * cell
    return hq, wq, (hq - hp) // 2, (wq - wp) // 2


@dataclass
class _Level:
    weight: object
    sum_z: object
    sum_rgb: list
    zlo: object  # nearest surfel depth in the cell (inf: none)
    zhi: object  # farthest kept surfel depth (-inf: none)
    label: object | None  # label of the nearest kept child


def _pull(ops, lev: _Level, p: VisibilityParams) -> _Level:
    """One coarser level: each cell keeps the children within the depth tolerance of its nearest
    child (by mean depth). The four children are stacked on a leading axis (order (0, 0), (0, 1),
    (1, 0), (1, 1)) and summed one by one in that order, so that every backend rounds alike."""
    inf = float("inf")
    w4 = ops.children(lev.weight)
    mean = ops.where(w4 > 0, ops.children(lev.sum_z) / ops.where(w4 > 0, w4, 1.0), inf)
    front = ops.minimum(ops.minimum(mean[0], mean[1]), ops.minimum(mean[2], mean[3]))
    keep = mean <= (front * p.tol_rel1 + p.tol_abs_m)[None]
    k = ops.as_f32(keep)

    def total(a4):
        return a4[0] + a4[1] + a4[2] + a4[3]

    weight = total(w4 * k)
    sum_z = total(ops.children(lev.sum_z) * k)
    sum_rgb = [total(ops.children(c) * k) for c in lev.sum_rgb]
    lo4 = ops.where(keep, ops.children(lev.zlo), inf)
    hi4 = ops.where(keep, ops.children(lev.zhi), -inf)
    zlo = ops.minimum(ops.minimum(lo4[0], lo4[1]), ops.minimum(lo4[2], lo4[3]))
    zhi = ops.maximum(ops.maximum(hi4[0], hi4[1]), ops.maximum(hi4[2], hi4[3]))
    label = None
    if lev.label is not None:
        # The label of the nearest kept child (the first one in the fixed order on ties).
        l4 = ops.children(lev.label)
        nearest = keep & (mean == front[None])
        label = ops.where(nearest[3], l4[3], -1)
        for i in (2, 1, 0):
            label = ops.where(nearest[i], l4[i], label)
    return _Level(weight, sum_z, sum_rgb, zlo, zhi, label)


def point_tree(xyz: np.ndarray):
    """The k-d tree (scipy's cKDTree) of the points, which the neighbour queries below take (``tree``)
    so that a map's load builds it once for its spacing, normals and sides, not once each."""
    from scipy.spatial import cKDTree

    return cKDTree(np.asarray(xyz, np.float64))


def point_spacing(xyz: np.ndarray, neighbours: int = 4, lo_m: float = 0.002, hi_m: float = 0.1,
                  tree=None) -> np.ndarray:
    """Local point spacing per point (float32, metres): the mean distance to its ``neighbours``
    nearest points, between ``lo_m`` and ``hi_m`` (an isolated outlier does not get a huge disk).
    ``tree``: :func:`point_tree` of ``xyz``, where the caller has it."""
    tree = point_tree(xyz) if tree is None else tree
    dist, _ = tree.query(xyz, k=neighbours + 1, workers=-1)
    return np.clip(dist[:, 1:].mean(axis=1), lo_m, hi_m).astype(np.float32)


def point_normals(xyz: np.ndarray, neighbours: int = 10, tree=None) -> np.ndarray:
    """Unit surface normal per point (float32 (N, 3), sign arbitrary): the direction of least
    variance of the point and its ``neighbours`` nearest points (principal component analysis,
    Hoppe et al. 1992, "Surface reconstruction from unorganized points").

    Unoriented: the visibility test needs only how steeply a surface is seen (its slope), which
    does not depend on the normal's sign; :func:`orient_normals` turns them towards the side the
    robot saw where the map records it. The neighbourhood (~4 cm at the maps' 2.6 cm spacing)
    stays on one face of a 10 cm wall."""
    return point_spacing_and_normals(xyz, 1, neighbours, tree=tree)[1]


def orient_normals(normals: np.ndarray, view_dirs: np.ndarray | None,
                   min_agreement: float) -> tuple[np.ndarray, np.ndarray]:
    """(normals float32 (N, 3), sided uint8 (N,)): unoriented ``normals`` turned towards the side
    each point was seen from, its mean direction towards the cameras that saw it
    (``PointCloud.view_dirs``, int8). As in normal orientation towards the scanner's viewpoint
    (Hoppe et al. 1992 orient by propagation where no viewpoint is known; a range scan's points
    know theirs), but with the mean of all the viewpoints a fused point had. A point's side is
    known (``sided`` 1) where that mean direction lies at least ``min_agreement`` (a cosine times
    its length) off the surface's plane: a thin object seen from both sides, or a point whose
    viewpoints scatter along its plane, has none. Without ``view_dirs`` no side is known."""
    normals = np.asarray(normals, np.float32)
    if view_dirs is None:
        return normals, np.zeros(len(normals), np.uint8)
    from shared.cloud import view_dirs_unit

    agree = np.einsum("ij,ij->i", normals, view_dirs_unit(view_dirs))
    oriented = np.where((agree < 0)[:, None], -normals, normals).astype(np.float32)
    return oriented, (np.abs(agree) >= min_agreement).astype(np.uint8)


def vote_sides(xyz: np.ndarray, normals: np.ndarray, sided: np.ndarray, neighbours: int,
               min_vote: float, chunk: int = 1 << 14, tree=None) -> tuple[np.ndarray, np.ndarray]:
    """(normals float32 (N, 3), sided uint8 (N,)): the side of each point decided by its
    ``neighbours`` nearest points (itself included), not by its own normal alone. Each sided
    neighbour votes with its oriented normal (:func:`orient_normals`); a point's side, and its
    normal (the slope test's too), is the mean vote's direction, known where that mean is at least
    ``min_vote`` long (the neighbours agree); elsewhere its own normal stays, with no side.

    Why: on a depth-noise map a wall's face is a slab of points a few cm thick, and the normal of
    ten of them points anywhere within it. Oriented one by one, the far face of a wall the robot
    saw from one room only then draws as a mottle of unseen grey and the next room's paint. Their
    mean over a neighbourhood keeps the slab's direction (the tilts cancel, the side does not); the
    two faces of a thin object, oriented apart, cancel to no side, as one point of it has none."""
    xyz = np.asarray(xyz, np.float64)
    k = min(neighbours, len(xyz))
    if k < 2:
        return np.asarray(normals, np.float32), np.asarray(sided, np.uint8)
    tree = point_tree(xyz) if tree is None else tree  # (:func:`point_tree`)
    votes = np.where(np.asarray(sided, bool)[:, None], normals, np.float32(0.0)).astype(np.float32)
    out_n = np.asarray(normals, np.float32).copy()
    out_s = np.zeros(len(xyz), np.uint8)
    for lo in range(0, len(xyz), chunk):
        # Queried a chunk at a time: all the neighbours at once were (N, k) int64, 200 MB for a
        # 1.6 M-point map, for no gain (each point's neighbours are its own).
        _, nbr = tree.query(xyz[lo : lo + chunk], k=k, workers=-1)
        mean = votes[nbr].mean(axis=1)  # (c, 3)
        length = np.sqrt(np.einsum("ij,ij->i", mean, mean))
        known = length >= min_vote
        out_n[lo : lo + chunk][known] = mean[known] / length[known, None]
        out_s[lo : lo + chunk] = known
    return out_n, out_s


def point_spacing_and_normals(xyz: np.ndarray, spacing_neighbours: int = 4, normal_neighbours: int = 10,
                              chunk: int = 1 << 14, tree=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`point_spacing` and :func:`point_normals` from one nearest-neighbour query (a map's
    load pays for one tree and one query, not two); the spacing is the one ``point_spacing``
    returns, to the bit (the nearest distances of a longer query are the same values).

    ``chunk``: points whose normals are solved at a time; each point's are its own, so any chunk
    gives the same bits. 16k keeps each (chunk, k, 3) temporary at ~4 MB, under the allocator's
    mmap threshold: at 131k (35 MB) every temporary was a fresh mapping whose pages the kernel
    zeroed on first touch, and a 400k-point cloud took 3.2-4.1 s of CPU (1.2-1.6 s of it system
    time) against 2.0 s."""
    xyz = np.asarray(xyz, np.float64)
    k = min(max(normal_neighbours, spacing_neighbours) + 1, len(xyz))
    tree = point_tree(xyz) if tree is None else tree  # (:func:`point_tree`)
    dist, nbr = tree.query(xyz, k=k, workers=-1)
    dist, nbr = dist.reshape(len(xyz), k), nbr.reshape(len(xyz), k)
    if k - 1 < spacing_neighbours:
        # Fewer points than neighbours asked for: point_spacing's query pads with infinite
        # distances, so every point gets the upper clip; say so here rather than average an empty
        # or short slice (a one-point map made NaN radii, which no table lookup survives).
        spacing = np.full(len(xyz), 0.1, np.float32)
    else:
        spacing = np.clip(dist[:, 1 : spacing_neighbours + 1].mean(axis=1), 0.002, 0.1).astype(np.float32)
    kn = min(normal_neighbours + 1, k)
    normals = np.empty((len(xyz), 3), np.float32)
    for lo in range(0, len(xyz), chunk):
        normals[lo : lo + chunk] = pca_normals(xyz[nbr[lo : lo + chunk, :kn]])  # (c, k, 3) neighbourhoods
    return spacing, normals


@dataclass(frozen=True)
class _Plan:
    """What :func:`compose_compiled` needs of a view's size and parameters alone: built once per
    (parameters, size), not per view (~0.3 ms of Python per view otherwise)."""

    levels: int
    oy: int
    ox: int
    lut: np.ndarray  # radius_lut
    fill_hi: np.ndarray  # per-level constants of the push
    fill_lo: np.ndarray
    gap_rel: np.ndarray
    gap_scale: np.ndarray
    dims: np.ndarray  # (levels + 1, 2) cells per level
    offs: np.ndarray  # level lev's cells start at row offs[lev] of the stored levels 1..
    taps: np.ndarray  # FILTER_TAPS' weights
    erode_kernels: tuple  # the min filters' windows by size - 1


@functools.lru_cache(maxsize=64)
def _plan(p: VisibilityParams, h: int, w: int) -> _Plan:
    f32 = np.float32
    levels = max(p.fill_levels, p.gap_levels)
    hq, wq, oy, ox = pyramid_grid(h, w, levels)
    # Per-level constants of the push, rounded to float32 exactly as numpy rounds a Python float
    # that meets a float32 array.
    tol_rel = p.tol_rel1 - 1.0
    fill_hi, fill_lo, gap_rel, gap_scale = (np.zeros(levels + 1, f32) for _ in range(4))
    for lev in range(1, levels + 1):
        half_slope = p.slope_per_px * min(1 << (lev - 1), SLOPE_CELL_PX)
        full_slope = p.slope_per_px * min(1 << lev, SLOPE_CELL_PX)
        rel = tol_rel + half_slope
        fill_hi[lev], fill_lo[lev] = 1.0 + rel, 1.0 - rel
        gap_rel[lev] = tol_rel + full_slope
        gap_scale[lev] = (1 << lev) / p.focal_px
    dims = np.array([(hq >> lev, wq >> lev) for lev in range(levels + 1)], np.int64)
    offs = np.zeros(levels + 2, np.int64)  # level 0 is not stored: offs[0] = offs[1] = 0
    for lev in range(1, levels + 1):
        offs[lev + 1] = offs[lev] + dims[lev, 0] * dims[lev, 1]
    taps = np.array([t[2] for t in FILTER_TAPS], f32)
    kern = tuple(np.ones((m + 1, m + 1), np.uint8) for m in range(p.max_radius_px + 1))
    for a in (p_ for p_ in (fill_hi, fill_lo, gap_rel, gap_scale, dims, offs, taps, *kern)):
        a.setflags(write=False)  # shared by every view (and thread) of this size
    return _Plan(levels, oy, ox, radius_lut(p), fill_hi, fill_lo, gap_rel, gap_scale, dims, offs, taps, kern)


def compose_compiled(front: FrontLayer, p: VisibilityParams, h: int, w: int, nearest=None, point_labels=None):
    """:func:`compose` on numpy arrays through the compiled loops of :mod:`visibility_kernels`
    (bit-identical; ~10x faster at 256 x 256). Same outputs. Labels come from ``front.label``, or,
    when that is None and ``nearest`` is given, as ``point_labels[nearest]`` (``nearest``: the
    front layer's image of each pixel's nearest point id, -1: none): only the visible pixels read
    one, where a label image costs a pass over every pixel of the guard-band grid."""
    import cv2

    from libs.pointrender import visibility_kernels as vk

    plan = _plan(p, h, w)
    f32 = np.float32
    g = p.guard_px
    # Footprint classes and covers on the front layer's grid (the padded image and its guard
    # band): the pyramid's extra pixels hold no surfel, so no footprint reaches past it (the
    # erosion's border is the same COVER_NONE).
    cls = np.empty(front.zmin.shape, np.int8)  # classes -1..48: a quarter of the bytes
    hist = np.zeros(p.max_radius_px + 1, np.int64)
    vk.classes(front.zmin, front.count, front.sum_spacing, f32(p.footprint_scale * p.focal_px),
               f32(p.min_radius_px), f32(p.max_radius_px), plan.lut, cls, hist)
    present = np.flatnonzero(hist).tolist()
    order, first = vk.bucket(cls, hist)
    # The four quadrant covers (16-bit depth codes), mirrored into one image so that one min
    # filter serves them all.
    # The min filters alternate between two buffers rather than allocate an image each.
    cov4 = np.full((*front.zmin.shape, 4), COVER_NONE, np.uint16)
    spare = np.empty_like(cov4)
    border = (COVER_NONE,) * 4
    inv_step, step = f32(1.0 / p.depth_step_m), f32(p.depth_step_m)
    for i, k in enumerate(reversed(present)):
        vk.add_codes(cov4, order, first[k], first[k + 1], front.zmin, inv_step)
        nxt = present[-2 - i] if i + 1 < len(present) else 0
        if k > nxt:
            m = k - nxt
            cv2.erode(cov4, plan.erode_kernels[m], dst=spare, anchor=(m, m), borderType=cv2.BORDER_CONSTANT,
                      borderValue=border)
            cov4, spare = spare, cov4
    reach = present[-1] if present else 0
    lab_direct = front.label is not None
    with_labels = lab_direct or nearest is not None
    # int32 ids and labels whatever the path (the kernel's nearest-point image is int32, the array code's
    # int64; a point id and a label fit): vk.finish has one signature (shared.jit.one_signature).
    i32 = np.int32
    lab_ids = front.label if lab_direct else (nearest if with_labels else np.full((1, 1), -1, i32))
    lab_ids = lab_ids if lab_ids.dtype == i32 else lab_ids.astype(i32)
    lab_table = np.asarray(point_labels, i32) if (with_labels and not lab_direct) else np.zeros(1, i32)
    with_slope = front.sum_slope is not None
    cells = int(plan.offs[-1])
    pyr = np.empty((cells, 8), f32)
    pyr_lab = np.empty(cells if with_labels else 1, np.int64)
    out_z = np.empty((h, w), f32)
    out_rgb = np.empty((3, h, w), f32)
    out_lab = np.empty((h, w) if with_labels else (1, 1), np.int64)
    hole = np.empty((h, w), bool)
    # Each pixel's enclosing depths from its four quadrant covers, unmirrored first (one
    # vectorised pass instead of four scattered reads per pixel in both passes that need them).
    q = cv2.split(cov4)
    q = (q[0], cv2.flip(q[1], 1), cv2.flip(q[2], 0), cv2.flip(q[3], -1))
    far_img = np.empty((h + 2, w + 2), f32)
    near_img = np.empty((h + 2, w + 2), f32)
    vk.enclosing(*q, step, g, reach, far_img, near_img)
    vk.finish(far_img, near_img, g, h, w, plan.oy, plan.ox, front.zmin, front.count, front.sum_z, front.sum_rgb[0],
              front.sum_rgb[1], front.sum_rgb[2], front.sum_slope if with_slope else front.zmin, with_slope,
              f32(p.slope_px), lab_ids, lab_table, with_labels, lab_direct, f32(p.tol_rel1), f32(p.tol_abs_m),
              plan.levels, plan.offs, plan.dims, pyr, pyr_lab, p.fill_levels, p.gap_levels, plan.fill_hi,
              plan.fill_lo, plan.gap_rel, plan.gap_scale, f32(p.gap_max_m), out_z, out_rgb, out_lab, hole)
    if p.filter_rel > 0:
        out_rgb = vk.colour_filter(out_rgb, out_z, hole, f32(p.filter_rel), plan.taps)
    return out_rgb, out_z, hole, out_lab if with_labels else None
