"""Compiled per-point passes of the ``layered`` splat (numba), bit-identical to the array version.

The array version in :mod:`splat` spends most of a view on work that only a loop does well: fancy
gathers of the visible points, a scatter-min (``np.minimum.at``), the per-pixel sums and the
temporaries between them. Here the same arithmetic runs as two loops over the culled,
level-of-detail-trimmed runs of the block index (no index array is ever built):

1. project every point, keep its target pixel, depth and quantised sub-pixel offset, and take the
   per-pixel minimum depth;
2. accumulate the front layer of each pixel (count, depth sum, colour sums, offset sums) and the
   nearest point's id for the label image.

Every operation reproduces the float32 / float64 rounding of the numpy expressions it replaces
(NEP 50 promotion: float32 arrays with Python floats stay float32; ``u - iu`` is float64; the
per-pixel sums are float32 sums in point order, as ``np.add.at`` adds them), so both paths give
the same images bit for bit and the tests compare them exactly. The kernels release the GIL, so
views of one step render on several threads at once.

numba is optional: :data:`AVAILABLE` is False when it is not installed and the renderer falls back
to the array path.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

from shared.jit import AVAILABLE, kernel


# The colour and offset sums are float32 sums of 8-bit values: exact (the integers the array code
# sums) while no pixel's front layer holds more than this many points (255 * n < 2^24); past it
# the caller falls back to the array code.
MAX_FRONT_POINTS = (1 << 24) // 255 - 1


def _project_run_py(xs, ys, zs, proj, near, far, w, h, qo, zo, uo, with_uv, pad=1):
    """Project one run of points: target pixel ``qo`` of the image padded by ``pad`` pixels on
    every side (the spare bin ``(h + 2 pad) * (w + 2 pad)`` for points that miss the padded image or
    the depth range), camera depth ``zo`` and, with ``with_uv``,
    the quantised sub-pixel offset ``uo`` (qu + 256 qv). Branch-free over the run so that it
    vectorises; out-of-range depths divide by one instead, so u, v stay finite and convert
    safely. Every pass that needs a point's pixel calls this, so all agree to the bit."""
    wp = w + 2 * pad
    a0, a1, a2, a3 = proj[0], proj[1], proj[2], proj[3]
    b0, b1, b2, b3 = proj[4], proj[5], proj[6], proj[7]
    c0, c1, c2, c3 = proj[8], proj[9], proj[10], proj[11]
    one = np.float32(1.0)
    half = np.float32(0.5)
    for i in range(xs.shape[0]):
        px, py, pz = xs[i], ys[i], zs[i]
        zc = px * c0 + py * c1 + pz * c2 + c3
        in_range = (zc > near) & (zc < far)
        inv = one / (zc if in_range else one)
        u = (px * a0 + py * a1 + pz * a2 + a3) * inv
        v = (px * b0 + py * b1 + pz * b2 + b3) * inv
        fu = np.floor(u + half)
        fv = np.floor(v + half)
        valid = in_range & (fu >= -pad) & (fu <= w - 1 + pad) & (fv >= -pad) & (fv <= h - 1 + pad)
        iu = np.int32(fu if valid else np.float32(-pad))
        iv = np.int32(fv if valid else np.float32(h + pad))  # (h + 2 pad) * wp + 0 = npad
        qo[i] = (iv + pad) * wp + (iu + pad)
        zo[i] = zc
        if with_uv:
            du = min(max(np.float64(u) - np.float64(fu) + 0.5, 0.0), 1.0) * 255.0
            dv = min(max(np.float64(v) - np.float64(fv) + 0.5, 0.0), 1.0) * 255.0
            uo[i] = np.int32(np.rint(du)) + 256 * np.int32(np.rint(dv))


_project_run = kernel(error_model="numpy")(_project_run_py) if AVAILABLE else _project_run_py


def _front_pass(
    x, y, z, rgb_packed, spacing, run_starts, run_counts, run_scale, proj, near, far, w, h, tol_rel1, tol_abs,
    with_labels, with_spacing, nx, ny, nz, slope_consts, with_slope, with_uv, pad=1,
    sided=None, unseen_cos=0.0, with_sides=False, unseen_rgb=0,
):
    """Both passes for one view over the points ``run_starts[r] : run_starts[r] + run_counts[r]``.

    Returns, per padded pixel plus one miss bin: the minimum depth (float32 (P,)); the front
    layer as float32 (P, 8): count, sums of depth, r, g, b, with ``with_spacing`` of
    ``spacing[p] * run_scale[r]``, with ``with_slope`` of each front point's depth slope
    (``renderer._point_slope`` of its normal ``nx, ny, nz`` and the view's ``slope_consts``), and in
    column 7, read as int32, the id of the nearest point (largest among ties, -1 where none):
    what ``accumulate_front`` returns, summed alike; the offset sums u, v as float32 (2, P) (only
    with ``with_uv``: the paper's 3x3 splat reads them, and the projection is cheaper without);
    and whether some pixel's front layer exceeded :data:`MAX_FRONT_POINTS`. A pixel no point
    reached (minimum depth inf) has zero sums and id -1.
    ``pad``: the pixels on each side of the image that points are projected into (1: the 3x3
    splat's ring; the visibility mode adds a guard band, :class:`splat.SplatConfig` ``guard_px``).
    ``with_sides``: a point whose side is known (``sided[p]``, its normal oriented towards the side
    the robot saw) adds the colour ``unseen_rgb`` (packed as ``rgb_packed``) instead of its own
    where this view sees its other side (``renderer._unseen_side``): it stays an occluder with its
    label, drawn in the colour of an unknown surface."""
    wp = w + 2 * pad
    npad = (h + 2 * pad) * wp
    n = 0
    for r in range(run_counts.shape[0]):
        n += run_counts[r]
    q_of = np.empty(n, np.int32)
    z_of = np.empty(n, np.float32)
    uv_of = np.empty(n if with_uv else 1, np.int32)  # qu + 256 qv
    one = np.float32(1.0)
    # Pass 1a, projection (:func:`_project_run`).
    k0 = 0
    for r in range(run_counts.shape[0]):
        s = run_starts[r]
        m = run_counts[r]
        _project_run(x[s : s + m], y[s : s + m], z[s : s + m], proj, near, far, w, h,
                     q_of[k0 : k0 + m], z_of[k0 : k0 + m], uv_of[k0 : k0 + m] if with_uv else uv_of, with_uv, pad)
        k0 += m
    # Pass 1b, per-pixel minimum depth. (np.empty and a fill, here and in the other pointrender kernels,
    # not np.full or np.zeros: numba compiles those two's implementations, each with an np.empty of its own,
    # for every signature, ~0.1 s of CPU each on a cold cache; a slice fill is lowered in place.)
    zbuf = np.empty(npad + 1, np.float32)
    zbuf[:] = np.inf
    for k in range(n):
        q = q_of[k]
        zbuf[q] = min(zbuf[q], z_of[k])
    # Pass 2a, the front layer: points behind it go to the spare bin too (vectorises: a gather).
    for k in range(n):
        q = q_of[k]
        q_of[k] = q if z_of[k] <= zbuf[q] * tol_rel1 + tol_abs else npad
    # Pass 2b, sums, in float32 and in point order (as ``accumulate_front`` adds them): one row
    # of eight per pixel (count, depth, r, g, b, spacing, slope, nearest id), so that a point
    # touches one cache line and the image passes read a pixel's surfel from one. Every row is
    # zeroed, in two strided fills: zeroing only the rows a point reached (a test and eight scalar
    # stores per pixel) does less work but does not vectorise, and the front pass took 1.16 ms
    # with it, 0.82 ms with the fills (the 1e6 flat's views, isolated).
    acc = np.empty((npad + 1, 8), np.float32)
    ids = acc.view(np.int32)  # column 7: the nearest point's id (largest among ties), -1: none
    acc[:, :7] = np.float32(0.0)
    ids[:, 7] = -1
    uv_sum = np.empty((2, npad + 1 if with_uv else 1), np.float32)  # offsets (the paper's splat)
    uv_sum[:] = np.float32(0.0)
    cx, cy, cz = slope_consts[0], slope_consts[1], slope_consts[2]
    ax, ay, az = slope_consts[3], slope_consts[4], slope_consts[5]
    inv_f, inv_tan = slope_consts[6], slope_consts[7]
    zero = np.float32(0.0)
    min_plane = np.float32(1e-6)
    most = np.float32(0.0)
    k = 0
    for r in range(run_counts.shape[0]):
        s = run_starts[r]
        scale = run_scale[r]
        for p in range(s, s + run_counts[r]):
            t = q_of[k]
            zc = z_of[k]
            uv = uv_of[k] if with_uv else np.int32(0)
            k += 1
            if t == npad:
                # Off the image or behind its pixel's front layer (~75 % of the drawn points on an
                # agent-built map: the far faces of walls, the rooms behind them): the spare bin
                # is never read, so these points need no sums.
                continue
            c = rgb_packed[p]
            d = zero
            if with_slope or with_sides:
                # n . (P - C): both the slope and the side test need it (renderer._point_slope).
                d = nx[p] * (x[p] - cx) + ny[p] * (y[p] - cy) + nz[p] * (z[p] - cz)
                if with_sides and sided[p] != 0 and d > zero:
                    dx, dy, dz = x[p] - cx, y[p] - cy, z[p] - cz
                    if d > unseen_cos * np.sqrt(dx * dx + dy * dy + dz * dz):
                        c = unseen_rgb
            acc[t, 0] += one
            acc[t, 1] += zc
            acc[t, 2] += np.float32(c & 0xFF)
            acc[t, 3] += np.float32((c >> 8) & 0xFF)
            acc[t, 4] += np.float32((c >> 16) & 0xFF)
            most = max(most, acc[t, 0])
            if with_spacing:
                acc[t, 5] += spacing[p] * scale
            if with_slope:
                # renderer._point_slope, operation for operation (d above).
                cc = nx[p] * ax + ny[p] * ay + nz[p] * az
                zs = zc * np.sqrt(max(one - cc * cc, zero))
                den = max(max(abs(d), zs * inv_tan), min_plane)
                acc[t, 6] += zc * (zs / den) * inv_f
            if with_uv:
                uv_sum[0, t] += np.float32(uv & 0xFF)
                uv_sum[1, t] += np.float32(uv >> 8)
            if with_labels and zc == zbuf[t]:
                ids[t, 7] = max(ids[t, 7], np.int32(p))
    return zbuf, acc, uv_sum, most > MAX_FRONT_POINTS


def _compose(chans, gx, gy, zpad, lab_pad, tol_rel1, tol_abs, rgb_out, depth_out, hole_out, labels_out,
             with_labels):
    """The image-space half of ``layered`` (``SplatRenderer._layered`` and the code after it),
    fused into one pass over the pixels: occlusion threshold from the 3x3 minimum depth, the nine
    Gaussian-weighted surfel contributions in the same order and float32 rounding as the array
    code, normalisation, and the nearest source's label. Writes into the ``*_out`` images."""
    h, w = depth_out.shape
    for i in range(h):
        for j in range(w):
            zmin = zpad[i, j]
            for r in range(i, i + 3):
                for c in range(j, j + 3):
                    zmin = min(zmin, zpad[r, c])
            thr = zmin * tol_rel1 + tol_abs
            a0 = a1 = a2 = a3 = a4 = np.float32(0.0)
            best_z = np.float32(0.0)
            best_l = -1
            first = True
            for oy in range(-1, 2):
                r = i + 1 - oy
                for ox in range(-1, 2):
                    c = j + 1 - ox
                    zs = zpad[r, c]
                    k = gx[ox + 1, r, c] * gy[oy + 1, r, c]
                    k = k if zs <= thr else np.float32(0.0)
                    a0 += chans[0, r, c] * k
                    a1 += chans[1, r, c] * k
                    a2 += chans[2, r, c] * k
                    a3 += chans[3, r, c] * k
                    a4 += chans[4, r, c] * k
                    if with_labels and (first or zs < best_z):
                        best_z = zs
                        best_l = lab_pad[r, c]
                    first = False
            if a0 > 0:
                hole_out[i, j] = False
                depth_out[i, j] = a1 / a0
                rgb_out[i, j, 0] = np.uint8(min(max(np.rint(a2 / a0), 0.0), 255.0))
                rgb_out[i, j, 1] = np.uint8(min(max(np.rint(a3 / a0), 0.0), 255.0))
                rgb_out[i, j, 2] = np.uint8(min(max(np.rint(a4 / a0), 0.0), 255.0))
                if with_labels:
                    labels_out[i, j] = best_l
            else:
                hole_out[i, j] = True
                depth_out[i, j] = 0.0
                rgb_out[i, j, 0] = rgb_out[i, j, 1] = rgb_out[i, j, 2] = 0
                if with_labels:
                    labels_out[i, j] = -1


def _labels_of(best, labels):
    """int64 image: ``labels[best]`` where ``best >= 0``, else -1 (``SplatRenderer._labels_pad``)."""
    out = np.empty(best.shape, np.int64)
    for i in range(best.shape[0]):
        for j in range(best.shape[1]):
            b = best[i, j]
            out[i, j] = labels[b] if b >= 0 else -1
    return out


def _visible_blocks(block_min, block_max, centre, radius, rot, t, normals, offsets, out):
    """``IndexedCloud.visible_blocks`` block by block: the bounding-sphere test settles most
    blocks, the eight corners of the box the rest (a block is out when all its corners lie
    outside one plane). ``rot``, ``t``: world_from_camera rotation and translation."""
    n_planes = normals.shape[0]
    norms = np.empty(n_planes)
    for k in range(n_planes):
        norms[k] = np.sqrt(normals[k, 0] ** 2 + normals[k, 1] ** 2 + normals[k, 2] ** 2)
    cam = np.empty(3)
    for b in range(block_min.shape[0]):
        # Camera-frame centre: (c - t) @ rot.
        for a in range(3):
            cam[a] = ((centre[b, 0] - t[0]) * rot[0, a] + (centre[b, 1] - t[1]) * rot[1, a]
                      + (centre[b, 2] - t[2]) * rot[2, a])
        out[b] = True
        sphere_in = True
        for k in range(n_planes):
            d = cam[0] * normals[k, 0] + cam[1] * normals[k, 1] + cam[2] * normals[k, 2] + offsets[k]
            if d > radius[b] * norms[k]:
                sphere_in = False
                break
        if not sphere_in:
            out[b] = False
            continue
        for k in range(n_planes):
            all_out = True
            for c in range(8):
                x = block_max[b, 0] if c & 4 else block_min[b, 0]
                y = block_max[b, 1] if c & 2 else block_min[b, 1]
                z = block_max[b, 2] if c & 1 else block_min[b, 2]
                d = offsets[k]
                for a in range(3):
                    ca = (x - t[0]) * rot[0, a] + (y - t[1]) * rot[1, a] + (z - t[2]) * rot[2, a]
                    d += ca * normals[k, a]
                if not d > 0:
                    all_out = False
                    break
            if all_out:
                out[b] = False
                break


if AVAILABLE:
    visible_blocks = kernel()(_visible_blocks)
    labels_of = kernel()(_labels_of)
    front_pass = kernel(error_model="numpy")(_front_pass)
    compose = kernel(error_model="numpy")(_compose)
else:  # pragma: no cover
    front_pass = compose = labels_of = visible_blocks = None


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """uint8 (N, 3) -> int32 (N,) ``r | g << 8 | b << 16``: one load per point in the kernel."""
    rgb = rgb.astype(np.int32)
    return np.ascontiguousarray(rgb[:, 0] | (rgb[:, 1] << 8) | (rgb[:, 2] << 16))


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernels; returns the seconds it took.

    A one-off per process: call it at service start so the first request does not pay for it."""
    if not AVAILABLE:
        return 0.0
    import time

    t0 = time.perf_counter()
    xyz = np.zeros((1, 3), np.float32)
    for with_spacing in (False, True):
        front_pass(
            xyz[:, 0], xyz[:, 1], xyz[:, 2], np.zeros(1, np.int32), np.ones(1, np.float32), np.zeros(1, np.int64),
            np.ones(1, np.int64), np.ones(1, np.float32), np.zeros(12, np.float32), np.float32(0.05),
            np.float32(20.0), 4, 4, np.float32(1.05), np.float32(0.1), True, with_spacing,
            xyz[:, 0], xyz[:, 1], xyz[:, 2], np.zeros(8, np.float32), with_spacing, not with_spacing,
            1, np.zeros(1, np.uint8), np.float32(0.15), with_spacing, np.int32(0),
        )
    f32 = np.ones((3, 6, 6), np.float32)
    compose(
        np.ones((5, 6, 6), np.float32), f32, f32, f32[0], np.zeros((6, 6), np.int64), np.float32(1.05),
        np.float32(0.1), np.empty((4, 4, 3), np.uint8), np.empty((4, 4), np.float32), np.empty((4, 4), bool),
        np.empty((4, 4), np.int32), True,
    )
    dt = time.perf_counter() - t0
    log.debug("splat kernels ready in %.2f s", dt)
    return dt
