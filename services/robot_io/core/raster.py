"""A z-buffer triangle rasteriser that answers pinhole image batches the way Embree's ``cast_rays`` does.

A panorama is 12 pinhole views from one point: a ray caster traverses a BVH for each of its 0.8 M
rays (at 256 px), while a rasteriser visits each visible triangle once per view and fills the
pixels it covers. On the simulator's generated houses that is 4-6x less CPU at 256 px and up to
2x at 64 px (``bench/robot_io.py`` prints both), and it runs in the calling thread, so robot
processes sharing a few cores do not also fight over Embree's worker pools.

**What it returns.** For every pixel, the three arrays :meth:`SceneRenderer.render` takes from
``cast_rays``, sampled at the rays of ``render._homogeneous_rays`` (pixel ``(i, j)`` looks along
``((j - cx) / fx, (i - cy) / fy, 1)`` in the camera frame - integer pixel coordinates, no half-pixel
offset - from the float32 camera centre Embree is given):

* ``t_hit`` float32: the ray parameter of the nearest hit, which is the z-depth because the rays have
  unit camera-z; ``inf`` at a miss;
* ``primitive_ids`` uint32: the triangle's index in the scene; ``0xFFFFFFFF`` at a miss;
* ``primitive_uvs`` float32: Embree's barycentrics ``(u, v)``, the weights of the triangle's
  *second* and *third* vertex (hit = ``(1 - u - v) v0 + u v1 + v v2``, checked against open3d in
  tests/unit/robot_io/test_raster.py); ``(0, 0)`` at a miss.

**How a pixel is decided (homogeneous rasterisation).** In the camera frame, with triangle vertices
``p0, p1, p2`` and a pixel ray ``d``, the edge functions ``E_k = d . (p_{k+1} x p_{k+2})`` and
``D = p0 . (p1 x p2)`` give the exact ray-triangle intersection: barycentrics ``E_k / S`` and
``t = D / S`` with ``S = E_0 + E_1 + E_2``. The ray hits (at ``t > 0``) iff every ``E_k`` has the sign
of ``D``. This needs no division by depth and no clipping, so triangles crossing or behind the
camera plane are exact; both faces are hit (Embree culls nothing); degenerate and edge-on
triangles (``D = 0``) are never hit (nor are they by Embree). Coverage is one fixed float64
expression per pixel, and two triangles sharing an edge compute exactly negated edge functions,
so a shared edge leaves no crack. Depth is compared as ``1 / t = S / D`` (linear in the pixel
coordinates); ``t``, ``u``, ``v`` are computed once per pixel, for the winning triangle.

**Near plane.** Hits nearer than ``near_m`` (default :data:`NEAR_M` = 0.1 mm) are ignored: the ray
passes through such a surface and sees what is behind it, where Embree would report it. A robot
of radius 0.1 m never has its camera within 0.1 mm of a surface. The near plane only bounds each
triangle's pixel rectangle (the part of the triangle in front of it is projected).

**Agreement with Embree (the tolerance tests/unit/robot_io/test_raster.py asserts).** Embree
intersects in float32, so the two can differ only where rounding decides:

* hit or miss: only on a ray within rounding of a silhouette edge (none measured on generated
  houses, Replica office0 or the Habitat test assets);
* which triangle: on >= 99.9 % of pixels the same, except coincident faces. Every other difference is
  a ray that meets both triangles at the same depth (a shared edge, a seam where two surfaces meet)
  or passes within 1e-3 (barycentric) of an edge. Coincident overlapping faces (the generated
  houses' overlapping door frames, the fridge asset) z-fight in both casters: Embree's winner
  follows its float32 rounding, ours the drawing order (the first drawn wins a tie); they disagree
  on 0.05-0.25 % of a house panorama's pixels and 1.5 % of the fridge's;
* where the triangle is the same: depth within 1e-5 relative, except at grazing incidence
  (cos < 0.02), where the depth of a float32-rounded ray moves by 1 / cos and the bound is 1e-6 on
  relative error x cos; u, v within 5e-3 (Embree's float32 barycentrics of small triangles); labels
  equal; colours equal on >= 99.9 % of those pixels (a vertex-colour blend rounding the other way,
  a texel boundary).

``python -m services.robot_io.tools.raster_parity`` prints these counts for any scene.

**Cost.** Per scene: triangles sorted along a Morton curve into chunks of :data:`CHUNK`, with a box
and the chunk's distinct vertices each. Per view: chunks outside the (one-pixel widened) frustum are
skipped, the rest drawn nearest first (ties in numba's argsort order: see :func:`_argsort`), each
distinct vertex transformed once; a chunk or triangle behind what is already drawn over its whole
rectangle is skipped (8 x 8 pixel tiles keep their farthest depth), as are triangles whose three
vertices are outside one frustum plane or whose rectangle holds no pixel centre. A remaining
triangle is set up once (three cross products) and filled row by row over its exact span: each edge
is solved for the row's bound in floating point, and only a bound within 1e-6 px of an integer is
settled by evaluating the per-pixel expression, so the span is exactly the covered set. One compiled
loop, single-threaded, GIL released: callers parallelise across robots.
"""

from __future__ import annotations

import math

import numpy as np

from shared.jit import AVAILABLE, kernel, numba

CHUNK = 32  # triangles per culling chunk: about the size of a wall segment or a furniture part
NEAR_M = 1e-4
MISS_ID = np.uint32(0xFFFFFFFF)
TILE = 8  # pixels per side of an occlusion tile
# Rounding allowance in pixels: projected rectangles are widened by it, and a span bound this close
# to an integer is settled by the exact per-pixel test.
SLACK_PX = 1e-6
_SETUP = 10  # per drawn triangle: 3 edge functions (a, b, c) over pixel (j, i), then |D|


def _morton3(q: np.ndarray) -> np.ndarray:
    """Interleave the bits of three 21-bit integer coordinates (N, 3) into one uint64 key."""
    out = np.zeros(len(q), np.uint64)
    q = q.astype(np.uint64)
    for bit in range(21):
        for axis in range(3):
            out |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return out


class RasterScene:
    """A scene's triangles prepared for rasterising pinhole views.

    ``vertices`` are taken as float32 (what Embree is given) and computed with in float64. The
    arrays are read-only after construction; :meth:`cast_views` uses scratch buffers of the
    instance, so one call at a time (the caller holds a lock).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, near_m: float = NEAR_M):
        if not AVAILABLE:
            raise RuntimeError("the rasteriser needs numba (shared.jit); use the embree ray caster")
        if not near_m > 0:
            raise ValueError(f"near_m must be positive, got {near_m}")
        self.near_m = float(near_m)
        v = np.asarray(vertices, np.float32).astype(np.float64)
        tris = np.asarray(triangles, np.int64).reshape(-1, 3)
        self.triangle_count = n = len(tris)
        corners = v[tris]  # (T, 3, 3)
        if n:
            # Morton order keeps each chunk of CHUNK triangles spatially compact: tight boxes.
            cen = corners.mean(axis=1)
            lo, hi = cen.min(axis=0), cen.max(axis=0)
            q = np.floor((cen - lo) / np.maximum(hi - lo, 1e-9) * (2**21 - 1)).astype(np.int64)
            order = np.argsort(_morton3(q), kind="stable")
        else:
            order = np.zeros(0, np.int64)
        self.tri_ids = order.astype(np.uint32)
        corners = corners[order]
        n_chunks = -(-n // CHUNK)
        self.chunk_lo = np.minimum(np.arange(n_chunks + 1, dtype=np.int64) * CHUNK, n)
        # Each chunk's distinct vertex positions, coordinate-major, and its triangles' corners as
        # indices into them: a view transforms a position once, not once per triangle using it (a
        # chunk of a generated house has ~48 distinct corners of its 96). The same float64 values
        # go through the same operations, so each corner's camera coordinates are the same bits.
        # Positions are told apart by their bits (0.0 and -0.0 are two: they can round differently).
        chunk_of = np.repeat(np.arange(n_chunks, dtype=np.uint64), CHUNK * 3)[:3 * n]
        keys = np.column_stack([chunk_of, corners.reshape(-1, 3).view(np.uint64)])
        uniq, inverse = np.unique(keys, axis=0, return_inverse=True)  # sorted by chunk first
        self.vert_lo = np.searchsorted(uniq[:, 0], np.arange(n_chunks + 1, dtype=np.uint64)).astype(np.int64)
        self.verts = np.ascontiguousarray(uniq[:, 1:].view(np.float64).T)
        self.tri_local = (inverse.reshape(-1) - self.vert_lo[chunk_of.astype(np.int64)]).astype(np.int32)
        # The last chunk padded with copies of its last triangle, which leave its box as it is.
        padded = np.concatenate([corners, np.repeat(corners[-1:], n_chunks * CHUNK - n, axis=0)])
        padded = padded.reshape(n_chunks, CHUNK * 3, 3)
        self.box_lo = np.ascontiguousarray(padded.min(axis=1))
        self.box_hi = np.ascontiguousarray(padded.max(axis=1))
        # Half the box diagonal, a hair more, so rounding never culls a visible box.
        self.box_rad = 0.5 * np.linalg.norm(self.box_hi - self.box_lo, axis=1) * (1 + 1e-9) + 1e-9
        self._setup = np.empty((max(n, 1), _SETUP), np.float64)
        self._setup_id = np.empty(max(n, 1), np.uint32)
        self._chunk_order = np.empty(n_chunks, np.int64)
        self._chunk_key = np.empty(n_chunks, np.float64)
        self._chunk_rank = np.empty(n_chunks, np.int64)
        self._chunk_rect = np.empty((n_chunks, 4), np.int64)
        self._cam = np.empty((5, CHUNK * 3), np.float64)  # x, y, z, column, row of a chunk's vertices
        self._code = np.empty(CHUNK * 3, np.int64)

    def cast_views(self, world_from_camera: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                   width_px: int, height_px: int) -> dict[str, np.ndarray]:
        """``cast_rays``' ``t_hit`` (B, H*W) float32, ``primitive_ids`` (B, H*W) uint32 and
        ``primitive_uvs`` (B, H*W, 2) float32 for (B, 4, 4) OpenCV world_from_camera poses."""
        poses = np.ascontiguousarray(np.asarray(world_from_camera, np.float64).reshape(-1, 4, 4))
        b, n = len(poses), width_px * height_px
        t = np.empty((b, n), np.float32)
        prim = np.empty((b, n), np.uint32)
        uv = np.empty((b, n, 2), np.float32)
        tiles = -(-width_px // TILE) * -(-height_px // TILE)
        _raster_kernel(self.verts, self.vert_lo, self.tri_local, self.tri_ids, self.chunk_lo, self.box_lo,
                       self.box_hi, self.box_rad, poses, float(fx), float(fy), float(cx), float(cy), int(width_px),
                       int(height_px), self.near_m, t, prim, uv, np.empty(n, np.float64), np.empty(n, np.int32),
                       self._setup, self._setup_id, np.empty(tiles, np.float64), np.empty(tiles, np.bool_),
                       self._chunk_order, self._chunk_key, self._chunk_rank, self._chunk_rect, self._cam, self._code)
        return {"t_hit": t, "primitive_ids": prim, "primitive_uvs": uv}


def _raster_kernel(verts, vert_lo, tri_local, tri_ids, chunk_lo, box_lo, box_hi, box_rad, poses, fx, fy, cx, cy,
                   w, h, near_m, t_out, prim_out, uv_out, wbuf, lbuf, setup, setup_id, tile_far, tile_dirty,
                   chunk_order, chunk_key, rank, crect, cam, code):  # pragma: no cover - compiled
    # Frustum side planes through the camera centre, widened by one pixel: inside is
    # xlo z <= x <= xhi z and ylo z <= y <= yhi z (camera frame).
    xlo, xhi = (-1.0 - cx) / fx, (w - cx) / fx
    ylo, yhi = (-1.0 - cy) / fy, (h - cy) / fy
    wmax = 1.0 / near_m
    # The same planes with unit normals (signed distances, for the spheres).
    g = 1.0 / math.sqrt(1.0 + xlo * xlo)
    nx0, nz0 = g, -xlo * g
    g = 1.0 / math.sqrt(1.0 + xhi * xhi)
    nx1, nz1 = -g, xhi * g
    g = 1.0 / math.sqrt(1.0 + ylo * ylo)
    ny2, nz2 = g, -ylo * g
    g = 1.0 / math.sqrt(1.0 + yhi * yhi)
    ny3, nz3 = -g, yhi * g
    qx, qy = cx / fx, cy / fy
    tx = (w + TILE - 1) // TILE
    ty = (h + TILE - 1) // TILE
    poly = np.empty((4, 3))
    corner = np.empty((8, 3))
    n_chunks = chunk_lo.shape[0] - 1
    cxs, cys, czs, cus, cvs = cam[0], cam[1], cam[2], cam[3], cam[4]
    for b in range(poses.shape[0]):
        r00, r01, r02 = poses[b, 0, 0], poses[b, 0, 1], poses[b, 0, 2]
        r10, r11, r12 = poses[b, 1, 0], poses[b, 1, 1], poses[b, 1, 2]
        r20, r21, r22 = poses[b, 2, 0], poses[b, 2, 1], poses[b, 2, 2]
        # Embree is given the float32 camera centre (render.write_rays): start the rays there too.
        ox = np.float64(np.float32(poses[b, 0, 3]))
        oy = np.float64(np.float32(poses[b, 1, 3]))
        oz = np.float64(np.float32(poses[b, 2, 3]))
        for q in range(w * h):
            wbuf[q] = 0.0
            lbuf[q] = -1
        for q in range(tx * ty):
            tile_far[q] = 0.0
            tile_dirty[q] = False
        # Chunks whose box meets the frustum, each with the pixel rectangle of its box (the whole
        # image when the box reaches behind the near plane), drawn nearest box corner first.
        n_vis = np.int64(0)  # not the literal 0, for which numba would compile _argsort a second time
        for c in range(n_chunks):
            # The box's circumscribed sphere first: one point to transform instead of eight.
            ex = 0.5 * (box_lo[c, 0] + box_hi[c, 0]) - ox
            ey = 0.5 * (box_lo[c, 1] + box_hi[c, 1]) - oy
            ez = 0.5 * (box_lo[c, 2] + box_hi[c, 2]) - oz
            rad = box_rad[c]
            x = r00 * ex + r10 * ey + r20 * ez
            y = r01 * ex + r11 * ey + r21 * ez
            z = r02 * ex + r12 * ey + r22 * ez
            if (z < near_m - rad or nx0 * x + nz0 * z < -rad or nx1 * x + nz1 * z < -rad
                    or ny2 * y + nz2 * z < -rad or ny3 * y + nz3 * z < -rad):
                continue
            inside = 0
            zmin = np.inf
            for m in range(8):
                ex = (box_hi[c, 0] if m & 1 else box_lo[c, 0]) - ox
                ey = (box_hi[c, 1] if m & 2 else box_lo[c, 1]) - oy
                ez = (box_hi[c, 2] if m & 4 else box_lo[c, 2]) - oz
                x = r00 * ex + r10 * ey + r20 * ez
                y = r01 * ex + r11 * ey + r21 * ez
                z = r02 * ex + r12 * ey + r22 * ez
                corner[m, 0], corner[m, 1], corner[m, 2] = x, y, z
                zmin = min(zmin, z)
                inside |= (z >= near_m) | ((x >= xlo * z) << 1) | ((x <= xhi * z) << 2) | ((y >= ylo * z) << 3) | ((y <= yhi * z) << 4)
            if inside != 31:  # all eight corners outside one plane
                continue
            if zmin >= near_m:
                u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
                for m in range(8):
                    u = fx * (corner[m, 0] / corner[m, 2]) + cx
                    v = fy * (corner[m, 1] / corner[m, 2]) + cy
                    u_lo, u_hi = min(u_lo, u), max(u_hi, u)
                    v_lo, v_hi = min(v_lo, v), max(v_hi, v)
                x0, x1, y0, y1 = _pixel_rect(u_lo, u_hi, v_lo, v_hi, w, h)
                if x0 > x1 or y0 > y1:
                    continue
                crect[c, 0], crect[c, 1], crect[c, 2], crect[c, 3] = x0, x1, y0, y1
            else:
                crect[c, 0], crect[c, 1], crect[c, 2], crect[c, 3] = 0, w - 1, 0, h - 1
            chunk_key[n_vis] = zmin
            chunk_order[n_vis] = c
            n_vis += 1
        _argsort(chunk_key, n_vis, rank)
        n_set = 0
        for oi in range(n_vis):
            c = chunk_order[rank[oi]]
            zc = chunk_key[rank[oi]]
            # np.bool_(False), not the constant False: numba compiles a constant argument as a
            # signature of its own (Literal[bool]), a second compile of _occluded beside the one for
            # the triangles' runtime flag below, for the same code.
            if zc >= near_m and _occluded(_w_bound(zc), crect[c, 0], crect[c, 1], crect[c, 2], crect[c, 3],
                                          wbuf, w, h, tile_far, tile_dirty, tx, np.bool_(False)):
                continue
            v0 = vert_lo[c]
            # The chunk's vertices in the camera frame, with the frustum planes each is outside of
            # and its pixel position (only used when the whole triangle is in front of the near plane).
            for q in range(vert_lo[c + 1] - v0):
                ex = verts[0, v0 + q] - ox
                ey = verts[1, v0 + q] - oy
                ez = verts[2, v0 + q] - oz
                x = r00 * ex + r10 * ey + r20 * ez
                y = r01 * ex + r11 * ey + r21 * ez
                z = r02 * ex + r12 * ey + r22 * ez
                cxs[q], cys[q], czs[q] = x, y, z
                code[q] = (z < near_m) | ((x < xlo * z) << 1) | ((x > xhi * z) << 2) | ((y < ylo * z) << 3) | ((y > yhi * z) << 4)
                iz = 1.0 / max(z, near_m)
                cus[q] = fx * (x * iz) + cx
                cvs[q] = fy * (y * iz) + cy
            for tri in range(chunk_lo[c], chunk_lo[c + 1]):
                m0, m1, m2 = tri_local[3 * tri], tri_local[3 * tri + 1], tri_local[3 * tri + 2]
                if code[m0] & code[m1] & code[m2]:
                    continue
                zmin = min(czs[m0], min(czs[m1], czs[m2]))
                crosses = zmin < near_m
                if not crosses:
                    u_lo, u_hi = min(cus[m0], min(cus[m1], cus[m2])), max(cus[m0], max(cus[m1], cus[m2]))
                    v_lo, v_hi = min(cvs[m0], min(cvs[m1], cvs[m2])), max(cvs[m0], max(cvs[m1], cvs[m2]))
                else:
                    # The projection of the part in front of the near plane bounds the pixels tried.
                    npoly = 0
                    for m in range(3):
                        ma, mb = tri_local[3 * tri + m], tri_local[3 * tri + (m + 1) % 3]
                        za, zb = czs[ma], czs[mb]
                        if za >= near_m:
                            poly[npoly, 0], poly[npoly, 1], poly[npoly, 2] = cxs[ma], cys[ma], za
                            npoly += 1
                        if (za >= near_m) != (zb >= near_m):
                            f = (near_m - za) / (zb - za)
                            poly[npoly, 0] = cxs[ma] + f * (cxs[mb] - cxs[ma])
                            poly[npoly, 1] = cys[ma] + f * (cys[mb] - cys[ma])
                            poly[npoly, 2] = near_m
                            npoly += 1
                    u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
                    for m in range(npoly):
                        u = fx * (poly[m, 0] / poly[m, 2]) + cx
                        v = fy * (poly[m, 1] / poly[m, 2]) + cy
                        u_lo, u_hi = min(u_lo, u), max(u_hi, u)
                        v_lo, v_hi = min(v_lo, v), max(v_hi, v)
                # A triangle between pixel centres ends here, before its edges are set up.
                x0, x1, y0, y1 = _pixel_rect(u_lo, u_hi, v_lo, v_hi, w, h)
                if x0 > x1 or y0 > y1:
                    continue
                big = (x1 // TILE - x0 // TILE + 1) * (y1 // TILE - y0 // TILE + 1) >= 4
                if not crosses and _occluded(_w_bound(zmin), x0, x1, y0, y1, wbuf, w, h, tile_far, tile_dirty, tx, big):
                    continue
                p0x, p0y, p0z = cxs[m0], cys[m0], czs[m0]
                p1x, p1y, p1z = cxs[m1], cys[m1], czs[m1]
                p2x, p2y, p2z = cxs[m2], cys[m2], czs[m2]
                # Edge k is p[k+1] x p[k+2]: every edge is a cross product of two cyclically
                # consecutive vertices, so a neighbour sharing it computes exactly its negation.
                e0x, e0y, e0z = p1y * p2z - p1z * p2y, p1z * p2x - p1x * p2z, p1x * p2y - p1y * p2x
                e1x, e1y, e1z = p2y * p0z - p2z * p0y, p2z * p0x - p2x * p0z, p2x * p0y - p2y * p0x
                e2x, e2y, e2z = p0y * p1z - p0z * p1y, p0z * p1x - p0x * p1z, p0x * p1y - p0y * p1x
                det = p0x * e0x + p0y * e0y + p0z * e0z
                if det == 0.0:
                    continue
                s = 1.0 if det > 0.0 else -1.0
                # E(j, i) = e . ((j - cx) / fx, (i - cy) / fy, 1) = a j + b i + c, signed so inside >= 0.
                a0, b0, c0 = s * (e0x / fx), s * (e0y / fy), s * ((e0z - e0x * qx) - e0y * qy)
                a1, b1, c1 = s * (e1x / fx), s * (e1y / fy), s * ((e1z - e1x * qx) - e1y * qy)
                a2, b2, c2 = s * (e2x / fx), s * (e2y / fy), s * ((e2z - e2x * qx) - e2y * qy)
                adet = abs(det)
                # Inverse depth S / |D|, linear over the image: the depth test needs no division.
                aw, bw, cw = (a0 + a1 + a2) / adet, (b0 + b1 + b2) / adet, (c0 + c1 + c2) / adet
                n0 = -1.0 / a0 if a0 != 0.0 else 0.0
                n1 = -1.0 / a1 if a1 != 0.0 else 0.0
                n2 = -1.0 / a2 if a2 != 0.0 else 0.0
                # The edges as tuples, for one loop over them in the rows below: one inlined copy of
                # _bound rather than three compiles ~0.7 s faster on a cold cache, draws as fast.
                ea, eb, ec, en = (a0, a1, a2), (b0, b1, b2), (c0, c1, c2), (n0, n1, n2)
                li = n_set
                drawn = False
                fx0, fx1 = float(x0), float(x1)
                for i in range(y0, y1 + 1):
                    fi = float(i)
                    # Each edge bounds the row's span on one side, exactly as the per-pixel
                    # expression ``a j + (b i + c) >= 0`` decides it (see _bound).
                    lo, hi = fx0, fx1
                    for k in range(3):
                        lo_k, hi_k = _bound(ea[k], eb[k] * fi + ec[k], en[k], fx0, fx1)
                        lo, hi = max(lo, lo_k), min(hi, hi_k)
                    jl = int(lo)
                    jh = int(hi)
                    if jl > jh:
                        continue
                    kw = bw * fi + cw
                    row = i * w
                    trow = (i // TILE) * tx
                    if not big:  # a few tiles at most: not worth testing them piece by piece
                        if _fill(wbuf, lbuf, row, jl, jh, aw, kw, li, crosses, wmax):
                            drawn = True
                            for tj in range(jl // TILE, jh // TILE + 1):
                                tile_dirty[trow + tj] = True
                        continue
                    j = jl
                    while j <= jh:
                        tj = j // TILE
                        je = min(jh, tj * TILE + TILE - 1)
                        # The tile's farthest surface (a lower bound: depths only come nearer) is
                        # nearer than this piece of the row at both ends, so at every pixel of it.
                        if tile_far[trow + tj] >= max(aw * j + kw, aw * je + kw):
                            j = je + 1
                            continue
                        if _fill(wbuf, lbuf, row, j, je, aw, kw, li, crosses, wmax):
                            tile_dirty[trow + tj] = True
                            drawn = True
                        j = je + 1
                if drawn:
                    setup[li, 0], setup[li, 1], setup[li, 2] = a0, b0, c0
                    setup[li, 3], setup[li, 4], setup[li, 5] = a1, b1, c1
                    setup[li, 6], setup[li, 7], setup[li, 8] = a2, b2, c2
                    setup[li, 9] = adet
                    setup_id[li] = tri_ids[tri]
                    n_set += 1
        # Resolve: t, u, v of the winning triangle, once per pixel.
        for i in range(h):
            fi = float(i)
            for j in range(w):
                q = i * w + j
                li = lbuf[q]
                if li < 0:
                    t_out[b, q] = np.inf
                    prim_out[b, q] = np.uint32(0xFFFFFFFF)
                    uv_out[b, q, 0] = 0.0
                    uv_out[b, q, 1] = 0.0
                    continue
                s0 = setup[li, 0] * j + (setup[li, 1] * fi + setup[li, 2])
                s1 = setup[li, 3] * j + (setup[li, 4] * fi + setup[li, 5])
                s2 = setup[li, 6] * j + (setup[li, 7] * fi + setup[li, 8])
                inv = 1.0 / (s0 + s1 + s2)
                t_out[b, q] = setup[li, 9] * inv
                prim_out[b, q] = setup_id[li]
                uv_out[b, q, 0] = s1 * inv
                uv_out[b, q, 1] = s2 * inv


def _fill(wbuf, lbuf, row, jl, jh, aw, kw, li, crosses, wmax):  # pragma: no cover - compiled
    """Depth-test pixels ``jl..jh`` of one row against inverse depth ``aw j + kw``; whether any was
    written. ``crosses``: the triangle reaches in front of the near plane (inverse depth > wmax)."""
    wrote = False
    if crosses:
        for j in range(jl, jh + 1):
            z = aw * j + kw
            if z > wbuf[row + j] and z <= wmax:
                wbuf[row + j] = z
                lbuf[row + j] = li
                wrote = True
    else:
        for j in range(jl, jh + 1):
            z = aw * j + kw
            if z > wbuf[row + j]:
                wbuf[row + j] = z
                lbuf[row + j] = li
                wrote = True
    return wrote


def _w_bound(zmin):  # pragma: no cover - compiled
    """An upper bound of the inverse depth computed anywhere on a surface whose depth is >= zmin
    (a hair above 1 / zmin: the per-pixel values carry rounding)."""
    return (1.0 / zmin) * (1.0 + 1e-9)


def _pixel_rect(u_lo, u_hi, v_lo, v_hi, w, h):  # pragma: no cover - compiled
    """The pixel centres (integer coordinates) inside a projected rectangle widened by SLACK_PX,
    clipped to the image: ``(x0, x1, y0, y1)``, empty when ``x0 > x1`` or ``y0 > y1``."""
    # Clamped to about the image before rounding: the projection of a vertex near the camera plane
    # can be any size.
    x0 = max(0, math.ceil(min(max(u_lo - SLACK_PX, -1.0), w)))
    x1 = min(w - 1, math.floor(min(max(u_hi + SLACK_PX, -1.0), w)))
    y0 = max(0, math.ceil(min(max(v_lo - SLACK_PX, -1.0), h)))
    y1 = min(h - 1, math.floor(min(max(v_hi + SLACK_PX, -1.0), h)))
    return x0, x1, y0, y1


def _occluded(w_near, x0, x1, y0, y1, wbuf, w, h, tile_far, tile_dirty, tx, refresh_all):  # pragma: no cover - compiled
    """Whether every pixel of the rectangle already holds a surface nearer than inverse depth
    ``w_near`` (a tie loses the depth test anyway: the first drawn wins).

    Tiles keep the farthest inverse depth of their pixels (0 while one is empty), possibly stale:
    depths only come nearer, so a stale value is a lower bound and still proves what it proves.
    Rescanning a tile costs as much as drawing a small triangle over it, so only ``refresh_all``
    (a triangle of several tiles, which then also skips its hidden tiles row by row) rescans the
    tiles of its rectangle written since their last scan.
    """
    occluded = True
    for ti in range(y0 // TILE, y1 // TILE + 1):
        for tj in range(x0 // TILE, x1 // TILE + 1):
            q = ti * tx + tj
            if tile_far[q] >= w_near:  # a stale value is a lower bound: enough when it proves it
                continue
            if tile_dirty[q] and refresh_all:
                far = np.inf
                for i in range(ti * TILE, min(h, ti * TILE + TILE)):
                    for j in range(tj * TILE, min(w, tj * TILE + TILE)):
                        far = min(far, wbuf[i * w + j])
                tile_far[q] = far
                tile_dirty[q] = False
            if tile_far[q] < w_near:
                occluded = False
                if not refresh_all:
                    return False
    return occluded


def _bound(a, k, neg_inv_a, lo, hi):  # pragma: no cover - compiled
    """``[lo, hi]`` narrowed to the integers ``j`` with ``a * j + k >= 0`` (as float64 evaluates it).

    ``-k / a`` puts the bound to within ~1e-12 px (pixel coordinates are small integers): rounding
    can only move it across an integer when it lies within ``SLACK_PX`` of one, and only then is the
    per-pixel expression evaluated to settle it. An empty range comes back as ``lo > hi``.
    """
    if a == 0.0:
        return (lo, hi) if k >= 0.0 else (hi + 1.0, hi)
    q = k * neg_inv_a
    if a > 0.0:
        if q <= lo - 1.0:
            return lo, hi
        if q > hi + 1.0:
            return hi + 1.0, hi
        j = math.ceil(q)
        if j - q < SLACK_PX or j - q > 1.0 - SLACK_PX:
            while a * (j - 1.0) + k >= 0.0:
                j -= 1.0
            while a * j + k < 0.0:
                j += 1.0
        return max(lo, j), hi
    if q >= hi + 1.0:
        return lo, hi
    if q < lo - 1.0:
        return hi + 1.0, hi
    j = math.floor(q)
    if q - j < SLACK_PX or q - j > 1.0 - SLACK_PX:
        while a * (j + 1.0) + k >= 0.0:
            j += 1.0
        while a * j + k < 0.0:
            j -= 1.0
    return lo, min(hi, j)


_SORT_SMALL = 15  # numba's quicksort sorts a range shorter than this by insertion
_SORT_STACK = 64  # the larger part is pushed, the smaller sorted first: the stack holds < log2(n) ranges


def _argsort(key, n, rank):  # pragma: no cover - compiled
    """``rank[:n]`` = ``np.argsort(key[:n])`` as numba compiles it, equal keys included.

    Chunks at the same nearest depth (one in five visible chunks in a generated house: boxes that
    share a corner) are drawn in this order, and the first drawn wins a z-fight, so the order of
    equal keys decides pixels: a stable sort changes some on every scene tried. This is numba's
    quicksort (numba/misc/quicksort.py: median of three, the larger part pushed, insertion sort
    below ``_SORT_SMALL``) step for step, so it puts equal keys where ``np.argsort`` did; written
    out with an array for its stack it compiles in a third of the time (0.5 s of CPU instead of 1.4)."""
    for i in range(n):
        rank[i] = i
    lo_stack = np.empty(_SORT_STACK, np.int64)
    hi_stack = np.empty(_SORT_STACK, np.int64)
    lo_stack[0], hi_stack[0] = 0, n - 1
    top = 1 if n >= 2 else 0
    while top > 0:
        top -= 1
        lo, hi = lo_stack[top], hi_stack[top]
        while hi - lo >= _SORT_SMALL:
            mid = (lo + hi) >> 1
            if key[rank[mid]] < key[rank[lo]]:
                rank[lo], rank[mid] = rank[mid], rank[lo]
            if key[rank[hi]] < key[rank[mid]]:
                rank[hi], rank[mid] = rank[mid], rank[hi]
            if key[rank[mid]] < key[rank[lo]]:
                rank[lo], rank[mid] = rank[mid], rank[lo]
            pivot = key[rank[mid]]
            rank[hi], rank[mid] = rank[mid], rank[hi]
            i, j = lo, hi - 1
            while True:
                while i < hi and key[rank[i]] < pivot:
                    i += 1
                while j >= lo and pivot < key[rank[j]]:
                    j -= 1
                if i >= j:
                    break
                rank[i], rank[j] = rank[j], rank[i]
                i += 1
                j -= 1
            rank[i], rank[hi] = rank[hi], rank[i]
            if hi - i > i - lo:
                if hi > i:
                    lo_stack[top], hi_stack[top] = i + 1, hi
                    top += 1
                hi = i - 1
            else:
                if i > lo:
                    lo_stack[top], hi_stack[top] = lo, i - 1
                    top += 1
                lo = i + 1
        for i in range(lo + 1, hi + 1):
            k = rank[i]
            v = key[k]
            j = i
            while j > lo and v < key[rank[j - 1]]:
                rank[j] = rank[j - 1]
                j -= 1
            rank[j] = k


if AVAILABLE:
    _argsort = kernel()(_argsort)
    _fill = numba.njit(nogil=True, cache=True, inline="always")(_fill)
    _w_bound = numba.njit(nogil=True, cache=True, inline="always")(_w_bound)
    _pixel_rect = numba.njit(nogil=True, cache=True, inline="always")(_pixel_rect)
    _bound = numba.njit(nogil=True, cache=True, inline="always")(_bound)
    _occluded = kernel()(_occluded)
    _raster_kernel = kernel()(_raster_kernel)
