"""Ground-truth scenes for tests, the benchmark and the pictures: a built coloured room, the
Replica office mesh, uniform sampling of a mesh into a labelled cloud, ray-cast reference views
and an RGB-D "reconstructed" cloud.

This stands in for the simulator (services/robot_io) so the renderer can be checked on its own;
both use open3d's RaycastingScene and the camera of :mod:`shared.geometry`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.cloud import PointCloud
from shared.cloud import sample_mesh as core_sample_mesh
from shared.geometry import PinholeCamera, camera_pose, depth_to_points


@dataclass
class LabelledMesh:
    """Triangles (float64 (T, 3, 3) world metres), per-vertex colours and per-triangle labels."""

    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int32
    colors: np.ndarray  # (V, 3) float64 in [0, 1]
    tri_labels: np.ndarray  # (T,) int32
    label_names: dict[int, str]


def _quad_grid(origin, eu, ev, nu: int, nv: int, color_fn):
    """A rectangle split into nu x nv quads, each with its own 4 vertices and flat colour."""
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    i, j = i.ravel(), j.ravel()
    du, dv = eu / nu, ev / nv
    base = origin + i[:, None] * du + j[:, None] * dv
    verts = np.stack([base, base + du, base + du + dv, base + dv], axis=1).reshape(-1, 3)
    cols = np.repeat(color_fn(i, j), 4, axis=0)
    k = np.arange(len(i))[:, None] * 4
    tris = np.concatenate([k + [0, 1, 2], k + [0, 2, 3]], axis=0)
    return verts, tris, cols


def built_room(seed: int = 0) -> LabelledMesh:
    """A 8 x 6 m, 2.7 m high two-room flat: a partition wall with a door splits it into a kitchen
    (x < 4) and a living room; boxes stand in for furniture. Every surface carries a pattern so that
    image comparisons see structure, and every triangle a label."""
    rng = np.random.default_rng(seed)
    names = {0: "kitchen floor", 1: "living room floor", 2: "wall", 3: "ceiling", 4: "table", 5: "sofa"}
    parts = []

    def add(origin, eu, ev, size_m, label, c0, c1):
        origin, eu, ev = (np.asarray(a, float) for a in (origin, eu, ev))
        nu = max(1, round(np.linalg.norm(eu) / size_m))
        nv = max(1, round(np.linalg.norm(ev) / size_m))
        c0, c1 = np.asarray(c0, float), np.asarray(c1, float)
        noise = rng.uniform(-0.06, 0.06, size=(nu * nv + 7, 3))

        def colour(i, j):
            checker = ((i + j) % 2)[:, None]
            return np.clip(c0 * (1 - checker) + c1 * checker + noise[i * nv + j], 0, 1)

        v, t, c = _quad_grid(origin, eu, ev, nu, nv, colour)
        parts.append((v, t, c, np.full(len(t), label, np.int32)))

    def box(lo, hi, label, c0, c1):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        dx, dy, dz = hi - lo
        ex, ey, ez = np.array([dx, 0, 0]), np.array([0, dy, 0]), np.array([0, 0, dz])
        add(lo, ex, ey, 0.25, label, c0, c1)
        add(lo + ez, ex, ey, 0.25, label, c0, c1)
        add(lo, ex, ez, 0.25, label, c0, c1)
        add(lo + ey, ex, ez, 0.25, label, c0, c1)
        add(lo, ey, ez, 0.25, label, c0, c1)
        add(lo + ex, ey, ez, 0.25, label, c0, c1)

    L, W, H = 8.0, 6.0, 2.7
    add([0, 0, 0], [4, 0, 0], [0, W, 0], 0.5, 0, [0.85, 0.8, 0.7], [0.55, 0.45, 0.35])  # kitchen tiles
    add([4, 0, 0], [4, 0, 0], [0, W, 0], 0.25, 1, [0.6, 0.35, 0.2], [0.45, 0.25, 0.15])  # parquet
    add([0, 0, H], [L, 0, 0], [0, W, 0], 1.0, 3, [0.95, 0.95, 0.95], [0.9, 0.9, 0.9])
    stripes = ([0.3, 0.5, 0.8], [0.8, 0.85, 0.9])
    add([0, 0, 0], [L, 0, 0], [0, 0, H], 0.4, 2, *stripes)
    add([0, W, 0], [L, 0, 0], [0, 0, H], 0.4, 2, [0.8, 0.4, 0.3], [0.9, 0.8, 0.6])
    add([0, 0, 0], [0, W, 0], [0, 0, H], 0.4, 2, [0.3, 0.7, 0.4], [0.8, 0.9, 0.7])
    add([L, 0, 0], [0, W, 0], [0, 0, H], 0.4, 2, [0.7, 0.6, 0.2], [0.9, 0.9, 0.6])
    # Partition at x = 4 with a 1 m door between y = 2.5 and 3.5 (both faces).
    for x in (3.95, 4.05):
        add([x, 0, 0], [0, 2.5, 0], [0, 0, H], 0.3, 2, [0.6, 0.3, 0.6], [0.85, 0.7, 0.85])
        add([x, 3.5, 0], [0, 2.5, 0], [0, 0, H], 0.3, 2, [0.6, 0.3, 0.6], [0.85, 0.7, 0.85])
    box([1.0, 0.5, 0.0], [2.2, 1.3, 0.8], 4, [0.2, 0.2, 0.6], [0.9, 0.5, 0.1])
    box([5.5, 4.2, 0.0], [7.5, 5.2, 0.6], 5, [0.1, 0.5, 0.3], [0.7, 0.2, 0.2])
    box([6.0, 1.0, 0.0], [6.6, 1.6, 1.1], 4, [0.9, 0.9, 0.2], [0.2, 0.2, 0.2])

    verts, tris, cols, labs, off = [], [], [], [], 0
    for v, t, c, lab in parts:
        verts.append(v), tris.append(t + off), cols.append(c), labs.append(lab)
        off += len(v)
    return LabelledMesh(
        np.concatenate(verts), np.concatenate(tris).astype(np.int32), np.concatenate(cols),
        np.concatenate(labs), names,
    )


def replica_office(data_dir: Path) -> LabelledMesh:
    """The Replica office0 mesh (vertex colours, no labels: every triangle is -1)."""
    from shared.o3d import o3d

    mesh = o3d.io.read_triangle_mesh(str(Path(data_dir) / "replica_office0" / "office0_mesh.ply"))
    tris = np.asarray(mesh.triangles, dtype=np.int32)
    return LabelledMesh(
        np.asarray(mesh.vertices, float), tris, np.asarray(mesh.vertex_colors, float),
        np.full(len(tris), -1, np.int32), {},
    )


def replica_poses(data_dir: Path) -> np.ndarray:
    """The recorded camera-to-world poses of Replica office0, (N, 4, 4), OpenCV camera axes."""
    return np.loadtxt(Path(data_dir) / "replica_office0" / "traj.txt").reshape(-1, 4, 4)


def sample_mesh(mesh: LabelledMesh, n_points: int, seed: int = 0) -> PointCloud:
    """Area-uniform samples of the mesh with interpolated colours and their triangle's label."""
    labels = mesh.tri_labels if (mesh.tri_labels >= 0).any() else None
    return core_sample_mesh(mesh.vertices, mesh.triangles, mesh.colors, labels, n_points=n_points, seed=seed,
                            label_names=mesh.label_names)


class RaycastCamera:
    """Ground-truth RGB-D-label views of a mesh by ray casting (open3d RaycastingScene)."""

    def __init__(self, mesh: LabelledMesh):
        from shared.o3d import o3d

        self._o3d = o3d
        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
        )

    def render(self, world_from_camera: np.ndarray, camera: PinholeCamera):
        """(rgb uint8 (H, W, 3), z-depth float32 (0 = miss), labels int32 (-1 = miss))."""
        rays_cam = camera.pixel_rays().reshape(-1, 3)  # z = 1, so t_hit is the z-depth
        dirs = rays_cam @ world_from_camera[:3, :3].T
        origin = np.broadcast_to(world_from_camera[:3, 3], dirs.shape)
        rays = np.concatenate([origin, dirs], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        t_hit = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy()
        hit = np.isfinite(t_hit)
        h, w = camera.height_px, camera.width_px
        rgb = np.zeros((h * w, 3), np.float32)
        labels = np.full(h * w, -1, np.int32)
        if hit.any():
            p = prim[hit]
            tv = self.mesh.colors[self.mesh.triangles[p]]  # (K, 3 vertices, 3)
            b = np.stack([1 - uv[hit, 0] - uv[hit, 1], uv[hit, 0], uv[hit, 1]], axis=1)
            rgb[hit] = np.einsum("kv,kvc->kc", b, tv)
            labels[hit] = self.mesh.tri_labels[p]
        depth = np.where(hit, t_hit, 0.0).astype(np.float32)
        rgb8 = np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
        return rgb8.reshape(h, w, 3), depth.reshape(h, w), labels.reshape(h, w)


def reconstructed_cloud(
    mesh: LabelledMesh,
    world_from_cameras: list[np.ndarray],
    camera: PinholeCamera = PinholeCamera(320, 240, 90.0),
    depth_noise_rel: float = 0.01,
    voxel_m: float = 0.01,
    seed: int = 0,
) -> PointCloud:
    """What RGB-D fusion of a recorded tour yields: back-projected ray-cast frames with relative
    depth noise, merged and thinned to one point per ``voxel_m`` voxel (holes where no frame looked)."""
    rng = np.random.default_rng(seed)
    cam = RaycastCamera(mesh)
    xyz, rgb, lab = [], [], []
    for wfc in world_from_cameras:
        c, d, l = cam.render(wfc, camera)
        d = d * (1.0 + depth_noise_rel * rng.standard_normal(d.shape)).astype(np.float32)
        pts, valid = depth_to_points(d, camera, wfc)
        xyz.append(pts.astype(np.float32)), rgb.append(c[valid]), lab.append(l[valid])
    xyz_a, rgb_a, lab_a = np.concatenate(xyz), np.concatenate(rgb), np.concatenate(lab)
    keys = np.floor(xyz_a / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    labels = lab_a[first] if (lab_a >= 0).any() else None
    return PointCloud(xyz_a[first], rgb_a[first], labels, dict(mesh.label_names))


def room_view_poses(n: int, seed: int = 0) -> list[tuple[tuple[float, float, float], float, float]]:
    """Agent poses (floor point, heading, pitch) inside the built room, clear of furniture."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        x, y = rng.uniform(0.6, 7.4), rng.uniform(0.6, 5.4)
        if abs(x - 4.0) < 0.4 or (0.8 < x < 2.4 and 0.3 < y < 1.5) or (5.3 < x < 7.7 and 4.0 < y < 5.4) \
                or (5.8 < x < 6.8 and 0.8 < y < 1.8):
            continue
        out.append(((x, y, 0.0), float(rng.uniform(-math.pi, math.pi)), float(rng.uniform(-0.2, 0.1))))
    return out


def replica_view_poses(data_dir: Path, n: int, stride: int = 97) -> list[np.ndarray]:
    """Every ``stride``-th recorded pose of the Replica trajectory (real camera placements)."""
    poses = replica_poses(data_dir)
    return [poses[i] for i in range(0, len(poses), stride)][:n]


__all__ = [
    "LabelledMesh", "RaycastCamera", "built_room", "camera_pose", "reconstructed_cloud",
    "replica_office", "replica_poses", "replica_view_poses", "room_view_poses", "sample_mesh",
]
