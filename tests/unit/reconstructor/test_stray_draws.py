"""Stray draws of a noisy region (issue 33): a voxel that holds a single depth draw beside a surface that
many draws placed is scatter, and goes; a surface only single draws saw stays; exact depth is untouched."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.reconstructor.core import RECONSTRUCTORS, RegionInput
from services.reconstructor.core.frames import PosedImage
from services.reconstructor.core.regional import _drop_stray_draws
from shared.cloud import PointCloud
from shared.geometry import PinholeCamera, camera_pose
from shared.schemas import Pose

WALL_X = 3.5


def _wall(rel: float, frames: int) -> RegionInput:
    """The wall x = 3.5 m seen head-on from the origin by ``frames`` frames, each with its own noise draw
    (sigma = rel * z^2: 12 cm raw at 3.5 m, ~2.5 cm denoised, so a voxel's draws spill into its neighbours)."""
    cam = PinholeCamera(256, 192, 90.0)
    images = []
    for i in range(frames):
        rng = np.random.default_rng(70 + i)
        wfc = camera_pose(np.array([0.0, 0.01 * i, 0.0]), 0.0, 0.0, 1.25)
        true = np.full((192, 256), WALL_X, np.float32)
        d = (true + rel * true**2 * rng.standard_normal(true.shape)).astype(np.float32) if rel else true
        rgb = np.full((192, 256, 3), 150, np.uint8)
        images.append(PosedImage(rgb=rgb, world_from_camera=wfc, camera=cam, depth_m=d, index=i, depth_noise_rel=rel))
    return RegionInput(0, Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0), images)


def test_single_draws_beside_a_supported_surface_go_and_lone_ones_stay():
    rng = np.random.default_rng(3)
    yz = np.stack(np.meshgrid(np.linspace(0.0, 1.0, 51), np.linspace(0.0, 1.0, 51)), -1).reshape(-1, 2)
    wall = np.column_stack([np.zeros(len(yz)), yz])  # x = 0, voxels 2 cm apart, well seen: 10 points each
    stray = np.column_stack([rng.choice([-0.04, 0.04], 50), rng.uniform(0.1, 0.9, (50, 2))])  # single draws 4 cm off
    lone = np.column_stack([np.full(30, 0.5), rng.uniform(0.0, 1.0, (30, 2))])  # a surface only single draws saw
    xyz = np.vstack([wall, stray, lone]).astype(np.float32)
    counts = np.concatenate([np.full(len(wall), 10), np.ones(50), np.ones(30)])
    cloud = PointCloud(xyz, np.zeros((len(xyz), 3), np.uint8))
    kept = _drop_stray_draws(cloud, counts, max_points=1, support_points=4, reach_m=0.06)
    assert len(kept) == len(wall) + 30
    assert (np.abs(kept.xyz[:, 0] - 0.04) > 0.001).all() and (np.abs(kept.xyz[:, 0] + 0.04) > 0.001).all()
    assert (kept.xyz[:, 0] == 0.5).sum() == 30


def test_a_noisy_wall_loses_its_scatter_not_its_surface():
    region = _wall(0.01, frames=16)  # fused in the far tier (denoised sigma > near_depth_noise_m)
    cfg = {"fusion": "voxels", "remove_outliers": False}  # the voxels' step (noisy depth's default is the TSDF)
    clouds = [RECONSTRUCTORS.create("rgbd", {**cfg, "stray_points": n}).reconstruct(region).cloud for n in (0, 1)]
    core = [(np.abs(c.xyz[:, 1]) < 2.0) & (np.abs(c.xyz[:, 2] - 1.25) < 1.0) for c in clouds]
    off_wall = [float((np.abs(c.xyz[m, 0] - WALL_X) > 0.045).mean()) for c, m in zip(clouds, core)]
    assert off_wall[0] > 0.1 and off_wall[1] < 0.7 * off_wall[0]
    # The wall itself stays mapped: a grid on it finds a point within 3 cm as often as without the rule.
    g = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 61), np.linspace(0.5, 2.0, 31)), -1).reshape(-1, 2)
    grid = np.column_stack([np.full(len(g), WALL_X), g])
    mapped = [float(np.isfinite(cKDTree(c.xyz).query(grid, distance_upper_bound=0.03)[0]).mean()) for c in clouds]
    assert mapped[1] >= mapped[0] - 0.02


def test_exact_depth_is_untouched():
    region = _wall(0.0, frames=2)
    a, b = (RECONSTRUCTORS.create("rgbd", {"stray_points": n}).reconstruct(region).cloud for n in (0, 2))
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb)
