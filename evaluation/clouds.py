"""The human-curated cloud of the paper's ablation: points sampled from the scene mesh itself.

The paper compares its agent-reconstructed cloud with the dataset's curated one; in our setting the
curated cloud is an area-uniform sample of the scene's surfaces with their true colours and semantic
labels, i.e. a reconstruction with no pose, scale or depth error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared import ply

from evaluation.errors import ConfigError


@dataclass(frozen=True)
class SampledCloud:
    """Points (N, 3) float32 metres, colours (N, 3) uint8, labels (N,) int32 (-1 unknown), label names."""

    xyz_m: np.ndarray
    rgb: np.ndarray
    labels: np.ndarray
    label_names: dict[int, str]

    def __len__(self) -> int:
        return len(self.xyz_m)


def sample_mesh_cloud(vertices: np.ndarray, triangles: np.ndarray, vertex_colors: np.ndarray,
                      triangle_labels: np.ndarray | None = None, *, density_per_m2: float = 300.0,
                      max_points: int = 1_000_000, seed: int = 0, texture=None,
                      label_names: dict[int, str] | None = None) -> SampledCloud:
    """Sample points uniformly by area over a triangle mesh (vectorised).

    Args:
        vertices: (V, 3) positions; triangles: (T, 3) vertex indices; vertex_colors: (V, 3) in [0, 1].
        triangle_labels: (T,) label per triangle (-1: unknown); None gives -1 everywhere.
        density_per_m2: points per square metre of surface, capped at ``max_points`` in total.
        texture: optional :class:`services.robot_io.core.scene.Texture`; textured triangles take the
            texel under the sample (nearest), the others their barycentric vertex colour.
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise ConfigError(f"need (V, 3) vertices and (T, 3) triangles, got {v.shape} and {t.shape}")
    if density_per_m2 <= 0 or max_points < 1:
        raise ConfigError("density_per_m2 and max_points must be positive")
    corners = v[t]  # (T, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    total = float(area.sum())
    if total <= 0:
        raise ConfigError("the mesh has no surface area")
    n = int(min(max_points, max(1, round(total * density_per_m2))))
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(t), size=n, p=area / total)
    # Uniform barycentrics by the square-root trick (Osada et al. 2002).
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)  # (n, 3)
    xyz = np.einsum("nk,nkd->nd", bary, corners[tri])
    cols = np.asarray(vertex_colors, np.float64)[t[tri]]  # (n, 3 corners, 3)
    rgb = np.einsum("nk,nkd->nd", bary, cols)
    if texture is not None:
        mids = np.asarray(texture.material_ids)[tri]
        for m in np.unique(mids[mids >= 0]):
            sel = np.flatnonzero(mids == m)
            img = texture.images[int(m)]
            uv = np.einsum("nk,nkd->nd", bary[sel], np.asarray(texture.triangle_uvs, np.float64)[tri[sel]])
            h, w = img.shape[:2]
            # Texture v runs upwards, image rows downwards.
            px = np.clip((uv[:, 0] % 1.0) * w, 0, w - 1).astype(np.int64)
            py = np.clip((1.0 - uv[:, 1] % 1.0) * h, 0, h - 1).astype(np.int64)
            rgb[sel] = img[py, px, :3] / 255.0
    labels = (np.full(n, -1, np.int32) if triangle_labels is None
              else np.asarray(triangle_labels, np.int32)[tri])
    return SampledCloud(xyz.astype(np.float32), np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8), labels,
                        dict(label_names or {}))


def sample_scene_cloud(scene, *, density_per_m2: float = 300.0, max_points: int = 1_000_000,
                       seed: int = 0) -> SampledCloud:
    """:func:`sample_mesh_cloud` over a :class:`services.robot_io.core.scene.Scene` (labels and names kept)."""
    return sample_mesh_cloud(scene.vertices, scene.triangles, scene.vertex_colors, scene.triangle_labels,
                             density_per_m2=density_per_m2, max_points=max_points, seed=seed,
                             texture=scene.texture, label_names=scene.label_names)


def cloud_ply_bytes(cloud: SampledCloud, with_labels: bool = True) -> bytes:
    """The cloud in the project's PLY layout (:mod:`shared.ply`, as ``GET /maps/{id}/cloud.ply`` serves it)."""
    labels = cloud.labels if with_labels else None
    return ply.encode(cloud.xyz_m, cloud.rgb, labels, cloud.label_names if with_labels else None)
