"""RGB-D-semantic rendering of a :class:`Scene` with open3d's Embree ray caster (or, for image
batches, the z-buffer rasteriser of :mod:`.raster`, which returns the same per-pixel hits).

The hot path (a 12-view panorama is ~0.8 M rays) is organised around what Embree needs and what
numpy does fast:

* **Rays in one pass.** The camera-frame pixel rays are cached per intrinsics in homogeneous form
  ``(x, y, 1, 1)``; a ``(B, 4, 6)`` matrix per view maps them to the whole ``(B, H*W, 6)`` origin +
  direction buffer, written in place (origin from the 4th column, direction = rotation of the unit-z
  ray) by one compiled loop (:func:`write_rays`). Directions have unit camera-z, so the ``t_hit``
  open3d returns *is* the z-depth; no per-pixel division.
* **One cast.** All views go to one ``cast_rays`` call (Embree parallelises across them).
* **Or no rays at all.** ``ray_caster="raster"`` (or ``"auto"`` where it is the cheaper, see
  :func:`resolve_ray_caster`) answers :meth:`SceneRenderer.render` with :class:`.raster.RasterScene`:
  the same ``t_hit`` / primitive id / barycentric uv per pixel (up to rounding on triangle edges and
  ties between coincident faces, see there), in the calling thread. Single rays, ``cast``,
  ``cast_shaded``, ``first_hit_distance`` and the navigation grid stay on Embree.
* **Lookups, not maths.** Colour (flat, barycentric vertex colours or texture), labels and the
  zeroing of misses are table lookups per pixel, fused into one compiled pass
  (:mod:`.shading`; numpy fallback with identical output).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np

from shared.geometry import PinholeCamera, camera_poses
from shared.jit import kernel
from shared.o3d import o3d

from .raster import RasterScene
from libs.world.scene import Scene
from .shading import AVAILABLE, ShadingTables, shade

log = logging.getLogger(__name__)

RayCaster = Literal["auto", "embree", "raster"]

# "auto" rasterises views of W x H pixels of scenes up to RASTER_TRIANGLES_PER_PIXEL * W * H triangles.
# The rasteriser's cost grows with the triangles in view, Embree's with the rays, so the crossover
# is a triangle count per pixel. Measured (CPU per 12-view panorama, raster / Embree, one run each,
# 2 shared cores): Replica office0 subdivided to 200 k triangles 0.45 at 256 px, 0.94 at 128 px,
# 2.0 at 64 px; to 800 k 0.88 / 1.9 / 3.9; a 3-floor 1,000 m2 house (60 k) 0.25 / 0.46 / 0.97;
# Replica office0 (50 k) 0.28 at 256 px, 0.95 at 64 px. They meet near 15 triangles per pixel
# (60 k at 64 px, 200-250 k at 128 px, ~1 M at 256 px); 12 keeps "auto" on the winning side.
RASTER_TRIANGLES_PER_PIXEL = 12


def resolve_ray_caster(name: RayCaster, triangle_count: int, pixels_per_view: int) -> Literal["embree", "raster"]:
    """The backend that ``name`` selects for views of ``pixels_per_view`` pixels of a scene of
    ``triangle_count`` triangles."""
    if name == "auto":
        fits = triangle_count <= RASTER_TRIANGLES_PER_PIXEL * pixels_per_view
        return "raster" if AVAILABLE and fits else "embree"
    if name not in ("embree", "raster"):
        raise ValueError(f"unknown ray caster {name!r}; known: auto, embree, raster")
    if name == "raster" and not AVAILABLE:
        raise RuntimeError("the raster ray caster needs numba; install it or use ray_caster='embree'")
    return name

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
def _homogeneous_rays(k: Intrinsics) -> np.ndarray:
    """(H*W, 4) float32 rows ``(x, y, 1, 1)``: the unit-z pixel ray plus a 1 that picks up the origin."""
    u = (np.arange(k.width_px, dtype=np.float64) - k.cx) / k.fx
    v = (np.arange(k.height_px, dtype=np.float64) - k.cy) / k.fy
    rays = np.ones((k.height_px, k.width_px, 4), dtype=np.float32)
    rays[:, :, 0] = u[None, :]
    rays[:, :, 1] = v[:, None]
    rays = rays.reshape(-1, 4)
    rays.setflags(write=False)
    return rays


def ray_matrices(world_from_camera: np.ndarray) -> np.ndarray:
    """(B, 4, 6) float32 maps from homogeneous pixel rays to ``[origin, direction]`` per pose."""
    poses = np.asarray(world_from_camera, dtype=np.float64).reshape(-1, 4, 4)
    m = np.zeros((len(poses), 4, 6), dtype=np.float32)
    m[:, 3, :3] = poses[:, :3, 3]
    m[:, :3, 3:] = np.transpose(poses[:, :3, :3], (0, 2, 1))
    return m


def _rays_kernel(rays, mats, out):  # pragma: no cover - compiled
    for b in range(mats.shape[0]):
        for i in range(rays.shape[0]):
            x, y, z, w = rays[i, 0], rays[i, 1], rays[i, 2], rays[i, 3]
            for j in range(6):
                out[b, i, j] = ((x * mats[b, 0, j] + y * mats[b, 1, j]) + z * mats[b, 2, j]) + w * mats[b, 3, j]


if AVAILABLE:
    _rays_kernel = kernel()(_rays_kernel)


def write_rays(rays: np.ndarray, mats: np.ndarray, out: np.ndarray, use_kernel: bool = True) -> None:
    """``out[b] = rays @ mats[b]`` in float32, as ``((x m0 + y m1) + z m2) + w m3`` per entry.

    Not a BLAS matmul: its worker threads spin while they wait, and with several robots on two cores
    the batched matmul took 0.3-0.8 s per panorama instead of 5 ms (measured, load 17). The compiled
    loop runs in the calling thread; without numba the same sums run as numpy passes. Both give the
    bytes the matmul gave here (float32, no fused multiply-add; the tests compare them).
    """
    if use_kernel and AVAILABLE:
        _rays_kernel(rays, mats, out)
        return
    r = rays[None, :, :, None]
    m = mats[:, None, :, :]
    np.multiply(r[:, :, 0], m[:, :, 0], out=out)
    out += r[:, :, 1] * m[:, :, 1]
    out += r[:, :, 2] * m[:, :, 2]
    out += r[:, :, 3] * m[:, :, 3]


class SceneRenderer:
    """Casts camera rays into one scene; thread-safe (one Embree scene, read-only after build).

    ``ray_caster`` picks what answers :meth:`render` (image batches): ``"embree"``, ``"raster"``
    or ``"auto"`` (per call, by the image size: :func:`resolve_ray_caster`); :meth:`caster_for`
    says which answers a given size. The rasteriser's tables are built on its first use.
    """

    def __init__(self, scene: Scene, nthreads: int = 0, use_kernel: bool = True, ray_caster: RayCaster = "auto"):
        self.scene = scene
        self.nthreads = nthreads
        self._rc = o3d.t.geometry.RaycastingScene()
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(scene.vertices.astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(scene.triangles.astype(np.int32))
        self._rc.add_triangles(mesh)
        resolve_ray_caster(ray_caster, len(scene.triangles), 1)  # a bad name fails here, not at the first view
        self.ray_caster = ray_caster
        self._raster: RasterScene | None = None
        self._tables = ShadingTables.build(scene.vertex_colors, scene.triangles, scene.triangle_labels, scene.texture)
        self.use_kernel = use_kernel
        self._tri_mean: np.ndarray | None = None
        self._buf: np.ndarray | None = None
        self._lock = threading.Lock()

    @property
    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        return self._rc

    @property
    def triangle_count(self) -> int:
        return self._tables.miss_row

    def caster_for(self, width_px: int, height_px: int) -> Literal["embree", "raster"]:
        """What :meth:`render` uses for views of this size."""
        return resolve_ray_caster(self.ray_caster, self.triangle_count, width_px * height_px)

    def triangle_colors(self) -> np.ndarray:
        """(T, 3) float32 mean vertex colour of each triangle, in [0, 1]."""
        if self._tri_mean is None:
            self._tri_mean = self.scene.vertex_colors[self.scene.triangles].mean(axis=1).astype(np.float32)
        return self._tri_mean

    # --- ray casting ---------------------------------------------------------------------------------

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (..., 3) + (..., 3); returns t_hit (inf = miss) and primitive ids / uvs."""
        rays = np.concatenate([np.broadcast_to(origins, directions.shape), directions], axis=-1).astype(np.float32)
        out = self._rc.cast_rays(o3d.core.Tensor(np.atleast_2d(rays)), nthreads=self.nthreads)
        return {k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs")}

    def cast_shaded(self, origins: np.ndarray, directions: np.ndarray, with_semantic: bool = False):
        """Cast rays (..., 3) and colour the hits like :meth:`render` does (textures, vertex and
        material colours): ``(t_hit (...) with inf at misses, rgb (..., 3) uint8, labels or None)``."""
        directions = np.asarray(directions, dtype=np.float32)
        shape = directions.shape[:-1]
        rays = np.concatenate([np.broadcast_to(np.asarray(origins, np.float32), directions.shape), directions], axis=-1)
        hit = self._rc.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays.reshape(-1, 6))), nthreads=self.nthreads)
        t = hit["t_hit"].numpy().copy()
        depth = t.copy()
        prim = hit["primitive_ids"].numpy().copy()
        rgb, sem = shade(self._tables, prim, hit["primitive_uvs"].numpy(), depth, with_semantic, use_kernel=self.use_kernel)
        return t.reshape(shape), rgb.reshape(*shape, 3), None if sem is None else sem.reshape(shape)

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
        if self.caster_for(w, h) == "raster":
            with self._lock:  # the rasteriser's scratch buffers
                if self._raster is None:
                    self._raster = RasterScene(self.scene.vertices, self.scene.triangles)
                hit = self._raster.cast_views(poses, k.fx, k.fy, k.cx, k.cy, w, h)
        else:
            mats = ray_matrices(poses)
            with self._lock:
                # A reused ray buffer: a fresh 20 MB allocation per panorama costs as much as the maths.
                if self._buf is None or self._buf.shape != (b, h * w, 6):
                    self._buf = np.empty((b, h * w, 6), np.float32)
                write_rays(_homogeneous_rays(k), mats, self._buf, self.use_kernel)
                out = self._rc.cast_rays(o3d.core.Tensor.from_numpy(self._buf), nthreads=self.nthreads)
            hit = {key: out[key].numpy() for key in ("t_hit", "primitive_ids", "primitive_uvs")}
        depth = hit["t_hit"].reshape(b, h, w)
        prim = hit["primitive_ids"].reshape(b, h, w)
        uv = hit["primitive_uvs"].reshape(b, h, w, 2)
        rgb, sem = shade(self._tables, prim, uv, depth, with_semantic, use_kernel=self.use_kernel)
        if single:
            return RenderOutput(rgb[0], depth[0], None if sem is None else sem[0])
        return RenderOutput(rgb, depth, sem)

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
        poses = camera_poses(position_m, headings_rad, pitch_rad, camera_height_m)
        return self.render(poses, camera, with_semantic=with_semantic)
