"""A noisy flat wall seen head-on by several frames: the fixture of the noisy-depth fusion tests
(surface thinning, TSDF), so each asks its own question of the same wall."""

from __future__ import annotations

import numpy as np

from services.reconstructor.core import RegionInput
from services.reconstructor.core.frames import PosedImage
from shared.geometry import PinholeCamera, camera_pose
from shared.schemas import Pose


def wall_frames(rel: float, wall_x: float, away_m: float, cam: PinholeCamera, back: int = 0, thick_m: float = 0.1,
                label: int | None = None) -> RegionInput:
    """Eight frames of the wall x = ``wall_x`` from ``away_m``, each its own noise draw (sigma = ``rel`` *
    depth^2); with ``back``, that many more look from the other side at the wall's far face, ``thick_m``
    behind, in another colour (and with ``label``, the next label)."""
    h, w = cam.height_px, cam.width_px
    images = []
    for i in range(8 + back):
        front = i < 8
        face = wall_x if front else wall_x + thick_m
        x, heading = (face - away_m, 0.0) if front else (face + away_m, np.pi)
        rng = np.random.default_rng(60 + i)
        wfc = camera_pose(np.array([x, 0.02 * (i % 4), 0.0]), heading, 0.0, 1.25)
        true = np.full((h, w), away_m, np.float32)
        d = (true + rel * true**2 * rng.standard_normal(true.shape)).astype(np.float32) if rel else true
        rgb = np.full((h, w, 3), 120 if front else 200, np.uint8)
        sem = None if label is None else np.full((h, w), label if front else label + 1, np.int32)
        images.append(PosedImage(rgb=rgb, world_from_camera=wfc, camera=cam, depth_m=d, semantic=sem, index=i,
                                 depth_noise_rel=rel))
    return RegionInput(0, Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0), images)
