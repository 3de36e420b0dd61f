"""Per-pixel comparison of the rasteriser with Embree's ``cast_rays`` over the same rays: where the
two disagree, and why (tests/unit/robot_io/test_raster.py asserts on these counts).

    python -m services.robot_io.tools.raster_parity [--scenes generated:0:area=200 ...] [--size 256]
        [--panoramas 8]

Per scene: panoramas (12 views, HFOV 90) from random walkable points at pitches 0, +45 and -45 deg;
the counts of :class:`Parity` summed over them.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

import numpy as np

from services.robot_io.core.raster import MISS_ID, RasterScene
from services.robot_io.core.render import Intrinsics, _homogeneous_rays, ray_matrices, write_rays
from libs.world.scene import Scene
from shared.o3d import o3d

EDGE_BARY = 1e-3  # a ray this close (in barycentric terms) to an edge of a triangle passes "on the edge"
DEPTH_RTOL = 1e-5
# At grazing incidence a depth moves by 1 / cos(incidence) times a direction error, and Embree is
# given float32 directions: there the bound is on relative depth error times cos(incidence).
GRAZING_COS = 0.02
DEPTH_RTOL_COS = 1e-6


@dataclass
class Parity:
    """Pixel counts of one comparison; the categories of ``prim_diff`` add up to it."""

    pixels: int
    miss_mismatch: int  # a hit in one, a miss in the other, of which:
    miss_off_edge: int  # ... farther than EDGE_BARY from the hit triangle's edges (a crack: none expected)
    prim_diff: int  # hits on different triangles, of which:
    same_point: int  # ... at the same depth: a shared edge, a seam, coincident faces
    zfight: int  # ...... of those, coincident (coplanar, overlapping) faces away from their edges
    edge: int  # ... at different depths, within EDGE_BARY of an edge of either triangle
    other: int  # ... anything else (none expected)
    depth_rel_max: float  # where the triangle is the same and the incidence is not grazing
    depth_rel_cos_max: float  # where the triangle is the same: relative depth error x cos(incidence)
    uv_abs_max: float  # where the triangle is the same

    @property
    def same_fraction(self) -> float:
        return 1.0 - self.prim_diff / self.pixels

    @property
    def same_but_zfight_fraction(self) -> float:
        """The same triangle, or one of two coincident faces (which one wins is arbitrary in both)."""
        return 1.0 - (self.prim_diff - self.zfight) / self.pixels

    def __add__(self, o: Parity) -> Parity:
        return Parity(*(a + b if isinstance(a, int) else max(a, b) for a, b in zip(vars(self).values(), vars(o).values())))


def rays_of(poses: np.ndarray, k: Intrinsics) -> np.ndarray:
    """(B * H * W, 6) float32 origin + direction: exactly the rays SceneRenderer.render gives Embree."""
    buf = np.empty((len(poses), k.width_px * k.height_px, 6), np.float32)
    write_rays(_homogeneous_rays(k), ray_matrices(poses), buf)
    return buf.reshape(-1, 6)


def embree_hits(rc: o3d.t.geometry.RaycastingScene, rays: np.ndarray) -> dict[str, np.ndarray]:
    out = rc.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
    return {key: out[key].numpy().reshape(len(rays), -1).squeeze(1) if key != "primitive_uvs" else out[key].numpy()
            for key in ("t_hit", "primitive_ids", "primitive_uvs")}


def raster_hits(raster: RasterScene, poses: np.ndarray, k: Intrinsics) -> dict[str, np.ndarray]:
    out = raster.cast_views(poses, k.fx, k.fy, k.cx, k.cy, k.width_px, k.height_px)
    return {"t_hit": out["t_hit"].reshape(-1), "primitive_ids": out["primitive_ids"].reshape(-1),
            "primitive_uvs": out["primitive_uvs"].reshape(-1, 2)}


def _min_bary(uv: np.ndarray) -> np.ndarray:
    return np.column_stack([1 - uv.sum(1), uv]).min(1)


def compare(scene: Scene, rays: np.ndarray, e: dict[str, np.ndarray], r: dict[str, np.ndarray]) -> Parity:
    pe, pr, te, tr = e["primitive_ids"], r["primitive_ids"], e["t_hit"], r["t_hit"]
    ue, ur = e["primitive_uvs"], r["primitive_uvs"]
    me, mr = pe == MISS_ID, pr == MISS_ID
    v = scene.vertices.astype(np.float32).astype(np.float64)

    def normals(ids):
        p = v[scene.triangles[ids]]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        return p, n / np.linalg.norm(n, axis=1, keepdims=True)

    diff = np.nonzero((pe != pr) & ~me & ~mr)[0]
    same_point = zfight = edge = other = 0
    if len(diff):
        (a, na), (_, nb) = normals(pe[diff]), normals(pr[diff])
        b = v[scene.triangles[pr[diff]]]
        at_same = np.abs(te[diff] - tr[diff]) <= DEPTH_RTOL * te[diff]
        coplanar = (np.abs((na * nb).sum(1)) > 1 - 1e-9) & (np.abs(((b - a[:, :1]) * na[:, None]).sum(2)).max(1) < 1e-6)
        near_edge = (_min_bary(ue[diff]) < EDGE_BARY) | (_min_bary(ur[diff]) < EDGE_BARY)
        same_point, zfight = int(at_same.sum()), int((at_same & coplanar & ~near_edge).sum())
        edge, other = int((~at_same & near_edge).sum()), int((~at_same & ~near_edge).sum())
    one = np.nonzero(me != mr)[0]
    uv_hit = np.where(me[one, None], ur[one], ue[one])
    miss_off_edge = int((_min_bary(uv_hit) >= EDGE_BARY).sum())
    same = np.nonzero((pe == pr) & ~me)[0]
    rel = np.abs(te[same] - tr[same]) / te[same]
    d = rays[same, 3:].astype(np.float64)
    cos = np.abs((normals(pe[same])[1] * d).sum(1)) / np.linalg.norm(d, axis=1)
    duv = np.abs(ue[same] - ur[same])
    steep = cos >= GRAZING_COS
    return Parity(len(pe), len(one), miss_off_edge, len(diff), same_point, zfight, edge, other,
                  float(rel[steep].max(initial=0.0)), float((rel * cos).max(initial=0.0)), float(duv.max(initial=0.0)))


def scene_parity(spec: str, size_px: int, panoramas: int, seed: int = 3) -> Parity:
    """:class:`Parity` of ``panoramas`` panoramas at random walkable points of a scene."""
    from services.robot_io.core.robot import SimConfig, SimRobot
    from shared.geometry import PinholeCamera, camera_poses, panorama_headings

    robot = SimRobot(SimConfig(scene=spec, ray_caster="embree"))
    raster = RasterScene(robot.scene.vertices, robot.scene.triangles)
    k = Intrinsics.from_pinhole(PinholeCamera(size_px, size_px, 90.0))
    rng = np.random.default_rng(seed)
    total = None
    for n in range(panoramas):
        pos = robot.nav.nodes_m[rng.integers(len(robot.nav.nodes_m))]
        pitch = math.radians((0.0, 45.0, -45.0)[n % 3])
        poses = camera_poses(pos, panorama_headings(rng.uniform(-math.pi, math.pi), 12), pitch, robot.config.camera_height_m)
        rays = rays_of(poses, k)
        p = compare(robot.scene, rays, embree_hits(robot.renderer.raycasting_scene, rays), raster_hits(raster, poses, k))
        total = p if total is None else total + p
    return total


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["generated:0:area=200", "generated:1:floors=2:area=160"])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--panoramas", type=int, default=8)
    args = ap.parse_args(argv)
    for spec in args.scenes:
        p = scene_parity(spec, args.size, args.panoramas)
        print(f"{spec}: {p.pixels} px; hit/miss differ {p.miss_mismatch} ({p.miss_off_edge} off an edge); "
              f"triangle differs {p.prim_diff} = same depth {p.same_point} (coincident faces {p.zfight}) "
              f"+ on an edge {p.edge} + other {p.other}; same triangle {100 * p.same_fraction:.3f} %, "
              f"or coincident {100 * p.same_but_zfight_fraction:.4f} %; where the same: depth rel <= "
              f"{p.depth_rel_max:.1e} (x cos <= {p.depth_rel_cos_max:.1e} at grazing), uv <= {p.uv_abs_max:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
