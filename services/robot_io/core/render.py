"""RGB-D-semantic rendering of a :class:`Scene` with open3d's Embree ray caster.

All views of a request are cast in one ``cast_rays`` call. Ray directions are the camera's unit-z
pixel rays rotated into the world, so the returned hit parameter *is* the z-depth (open3d measures
``t_hit`` in units of the direction's length); no per-pixel division is needed. Colour is the
barycentric interpolation of vertex colours, or a texture lookup through the triangle UVs; meshes
whose triangles are flat-coloured (the procedural houses) take a single gather per pixel.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import open3d as o3d

from shared.geometry import PinholeCamera, camera_pose

from .scene import Scene

log = logging.getLogger(__name__)

_INVALID = np.uint32(0xFFFFFFFF)


@dataclass
class RenderOutput:
    """Rendered views: rgb (B, H, W, 3) uint8, depth_m (B, H, W) float32 (0 = miss), semantic (B, H, W) int32."""

    rgb: np.ndarray
    depth_m: np.ndarray
    semantic: np.ndarray | None


@dataclass(frozen=True)
class Intrinsics:
    """General pinhole intrinsics (non-square pixels, off-centre principal point allowed)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width_px: int
    height_px: int

    @classmethod
    def from_pinhole(cls, cam: PinholeCamera) -> Intrinsics:
        return cls(cam.fx, cam.fy, cam.cx, cam.cy, cam.width_px, cam.height_px)


@lru_cache(maxsize=16)
def _pixel_rays(k: Intrinsics) -> np.ndarray:
    u = np.arange(k.width_px, dtype=np.float32)
    v = np.arange(k.height_px, dtype=np.float32)
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([(uu - k.cx) / k.fx, (vv - k.cy) / k.fy, np.ones_like(uu)], axis=-1)
    rays.setflags(write=False)
    return rays


class SceneRenderer:
    """Casts camera rays into one scene; thread-compatible (one Embree scene, read-only after build)."""

    def __init__(self, scene: Scene, nthreads: int = 0):
        self.scene = scene
        self.nthreads = nthreads
        self._rc = o3d.t.geometry.RaycastingScene()
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(scene.vertices.astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(scene.triangles.astype(np.int32))
        self._rc.add_triangles(mesh)
        tri_cols = scene.vertex_colors[scene.triangles]  # (T, 3 corners, 3)
        # Flat-coloured meshes skip the barycentric blend: one gather instead of three.
        self._flat = bool(np.all(np.abs(tri_cols - tri_cols[:, :1]).max(axis=(1, 2)) < 1.0 / 512))
        # uint8 colour per corner (+ a black row for misses), float for blending
        self._tri_rgb = np.vstack([np.round(tri_cols[:, 0] * 255).astype(np.uint8), np.zeros((1, 3), np.uint8)])
        self._tri_cols = np.ascontiguousarray(tri_cols, dtype=np.float32)
        self._labels = np.append(scene.triangle_labels, np.int32(-1)).astype(np.int32)
        self._tex = scene.texture
        self._normals = None
        self._buf: np.ndarray | None = None
        self._lock = threading.Lock()

    @property
    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        return self._rc

    def triangle_normals(self) -> np.ndarray:
        if self._normals is None:
            v = self.scene.vertices[self.scene.triangles]
            n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            self._normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return self._normals

    # --- ray casting ---------------------------------------------------------------------------------

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (..., 3) + (..., 3); returns t_hit (inf = miss) and primitive ids / uvs."""
        rays = np.concatenate([np.broadcast_to(origins, directions.shape), directions], axis=-1).astype(np.float32)
        out = self._rc.cast_rays(o3d.core.Tensor(np.atleast_2d(rays)), nthreads=self.nthreads)
        return {k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs")}

    def first_hit_distance(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance (in units of the direction length) to the first hit; inf where none."""
        directions = np.asarray(directions, dtype=np.float64)
        rays = np.concatenate([np.broadcast_to(origins, directions.shape), directions], axis=-1).astype(np.float32)
        t = self._rc.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6)), nthreads=self.nthreads)["t_hit"].numpy()
        return t.reshape(directions.shape[:-1]) if directions.ndim > 1 else float(t[0])

    # --- images --------------------------------------------------------------------------------------

    def render(self, world_from_camera: np.ndarray, intrinsics: Intrinsics | PinholeCamera, with_semantic: bool = True) -> RenderOutput:
        """Render one (4, 4) or a batch (B, 4, 4) of OpenCV world_from_camera poses."""
        k = intrinsics if isinstance(intrinsics, Intrinsics) else Intrinsics.from_pinhole(intrinsics)
        poses = np.asarray(world_from_camera, dtype=np.float64)
        single = poses.ndim == 2
        poses = poses[None] if single else poses
        b, h, w = len(poses), k.height_px, k.width_px
        rays_cam = _pixel_rays(k).reshape(-1, 3)
        with self._lock:
            # A reused ray buffer: fresh 20 MB allocations per panorama cost as much as the maths.
            if self._buf is None or self._buf.shape != (b, h * w, 6):
                self._buf = np.empty((b, h * w, 6), np.float32)
            buf = self._buf
            for i in range(b):
                buf[i, :, :3] = poses[i, :3, 3]
                np.matmul(rays_cam, poses[i, :3, :3].T.astype(np.float32), out=buf[i, :, 3:])
            hit = self._rc.cast_rays(o3d.core.Tensor.from_numpy(buf), nthreads=self.nthreads)
        depth = hit["t_hit"].numpy().reshape(b, h, w)
        prim = hit["primitive_ids"].numpy().reshape(b, h, w)
        miss = prim == _INVALID
        depth[miss] = 0.0  # t_hit is the z-depth because the directions have unit z
        prim[miss] = len(self._labels) - 1  # the extra "miss" row of every lookup table
        rgb = self._colour(prim, miss, hit)
        sem = self._labels[prim] if with_semantic else None
        if single:
            return RenderOutput(rgb[0], depth[0], None if sem is None else sem[0])
        return RenderOutput(rgb, depth, sem)

    def _colour(self, pid: np.ndarray, miss: np.ndarray, hit) -> np.ndarray:
        if self._flat and self._tex is None:
            return self._tri_rgb[pid]
        uv = hit["primitive_uvs"].numpy().reshape(*pid.shape, 2)
        safe = np.where(miss, 0, pid)
        w1, w2 = uv[..., 0:1], uv[..., 1:2]
        w0 = 1.0 - w1 - w2
        c = self._tri_cols[safe]  # (..., 3 corners, 3)
        rgb = w0 * c[..., 0, :] + w1 * c[..., 1, :] + w2 * c[..., 2, :]
        rgb = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if self._tex is not None:
            mids = self._tex.material_ids[safe]
            tuv = self._tex.triangle_uvs[safe]  # (..., 3, 2)
            st = w0 * tuv[..., 0, :] + w1 * tuv[..., 1, :] + w2 * tuv[..., 2, :]
            for m, img in enumerate(self._tex.images):
                sel = (mids == m) & ~miss
                if not sel.any():
                    continue
                h, w = img.shape[:2]
                s = st[sel]
                # Repeat-wrap like GL_REPEAT; glTF/OBJ v runs upwards, image rows downwards.
                px = np.floor((s[:, 0] % 1.0) * w).astype(np.int64).clip(0, w - 1)
                py = np.floor((1.0 - (s[:, 1] % 1.0)) * h).astype(np.int64).clip(0, h - 1)
                rgb[sel] = img[py, px]
        rgb[miss] = 0
        return rgb

    def render_views(
        self,
        position_m,
        headings_rad: np.ndarray,
        camera: PinholeCamera,
        pitch_rad: float | np.ndarray = 0.0,
        camera_height_m: float = 1.25,
        with_semantic: bool = True,
    ) -> RenderOutput:
        """Render views from one agent floor position at several headings (and pitches)."""
        headings = np.atleast_1d(np.asarray(headings_rad, dtype=np.float64))
        pitches = np.broadcast_to(np.asarray(pitch_rad, dtype=np.float64), headings.shape)
        poses = np.stack([camera_pose(position_m, h, p, camera_height_m) for h, p in zip(headings, pitches)])
        return self.render(poses, camera, with_semantic=with_semantic)
