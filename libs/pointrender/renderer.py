"""The splatting renderer (``SplatRenderer``) and its registry (``RENDERERS``: ``numpy``, ``torch``):
culling, level of detail, the front pass and the image-space passes of both modes, written once
against an array backend (:mod:`ops_numpy`, :mod:`ops_torch`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
import weakref
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from shared.geometry import DEFAULT_CAMERA_HEIGHT_M, PinholeCamera, camera_pose
from libs.pointrender import kernels, occlusion, visibility, visibility_kernels
from libs.pointrender.cloud import Frustum, IndexedCloud
from libs.pointrender.errors import BackendUnavailableError
from libs.pointrender.lod import VoxelLod, build_voxel_geometry, first_cell_m
from shared.registry import Registry
from shared.schemas import CameraIntrinsics, ViewPose

from libs.pointrender.config import LOD_CELL_PX, RenderedViews, SplatConfig, TorchSplatConfig
from libs.pointrender.ops_numpy import _NumpyOps, point_normals_of, point_sides_of, point_spacing_of
from libs.pointrender.ops_torch import _TorchOps

log = logging.getLogger(__name__)

_OFFSETS = [(oy, ox) for oy in (-1, 0, 1) for ox in (-1, 0, 1)]


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

    @property
    def _side_key(self) -> tuple:
        """The settings that decide the points' sides (cache keys of what follows from them)."""
        cfg = self.config
        return cfg.side_min_agreement, cfg.side_vote_neighbours, cfg.side_min_vote

    def _normals_of(self, index: IndexedCloud) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(normals, sided or None) of the index's points as views need them, or None."""
        cfg = self.config
        if self._with_sides(index):
            return point_sides_of(index, cfg.normal_neighbours, cfg.spacing_neighbours, cfg.side_min_agreement,
                                  cfg.side_vote_neighbours, cfg.side_min_vote)
        if self._with_slope:
            return point_normals_of(index, cfg.normal_neighbours, cfg.spacing_neighbours), None
        return None

    def _voxel_lod(self, index: IndexedCloud) -> VoxelLod | None:
        cfg = self.config
        if cfg.lod != "voxel" or cfg.lod_points_per_px is None:
            return None
        normals = self._normals_of(index)
        nn = None if normals is None else (cfg.normal_neighbours, *(self._side_key if normals[1] is not None else ()))
        key = ("voxel-lod", cfg.lod_cell_m, cfg.lod_cell_spacings, cfg.lod_levels, cfg.spacing_neighbours, nn)
        if key not in index.cache:
            spacing = point_spacing_of(index, cfg.spacing_neighbours)
            cell_m = first_cell_m(spacing, cfg.lod_cell_m, cfg.lod_cell_spacings)
            # The levels' points (np.unique per level, means, labels) do not depend on the normals:
            # renderers of other modes, normals or sides on one map share them and sum only their normals.
            geometry_key = ("voxel-geometry", cell_m, cfg.lod_levels, cfg.spacing_neighbours)
            if geometry_key not in index.cache:
                index.cache[geometry_key] = build_voxel_geometry(index, spacing, cell_m, cfg.lod_levels)
            geometry = index.cache[geometry_key]
            index.cache[key] = geometry.lod if normals is None else geometry.with_normals(*normals)
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
                   *(() if sided is None else self._side_key))
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
