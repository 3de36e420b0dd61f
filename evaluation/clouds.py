"""The human-curated cloud of the paper's ablation: points sampled from the scene mesh itself.

The paper compares its agent-reconstructed cloud with the dataset's curated one; in our setting the
curated cloud is an area-uniform sample of the scene's surfaces with their true colours and semantic
labels, i.e. a reconstruction with no pose, scale or depth error (the renderer core's
:func:`~shared.cloud.sample_mesh` does the sampling).
"""

from __future__ import annotations

import numpy as np

from evaluation.errors import ConfigError
from shared.cloud import PointCloud, sample_mesh


def sample_scene_cloud(scene, *, density_per_m2: float = 300.0, max_points: int = 1_000_000,
                       seed: int = 0) -> PointCloud:
    """A cloud of ``density_per_m2`` points per square metre of the scene's surfaces (at most
    ``max_points``), labels and label names kept."""
    if density_per_m2 <= 0 or max_points < 1:
        raise ConfigError("density_per_m2 and max_points must be positive")
    corners = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles, np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    n = int(min(max_points, max(1, round(float(area) * density_per_m2))))
    return sample_mesh(scene.vertices, scene.triangles, scene.vertex_colors, scene.triangle_labels, n_points=n,
                       seed=seed, texture=scene.texture, label_names=scene.label_names)
