"""View directions of built clouds: where each point was seen from, through fusion, emulation and alignment.

Scenes here are analytic (a box room, a bare plane) ray-cast exactly, so the true direction from every
point to the camera centre is known.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.reconstructor.core import (
    RECONSTRUCTORS,
    AlignmentReport,
    RegionalCloud,
    RegionInput,
    VoxelAccumulator,
    kernels,
    to_world,
    voxel_downsample,
)
from services.reconstructor.core.frames import PosedImage
from shared.cloud import PointCloud, quantise_view_dirs, view_dirs_unit
from shared.geometry import PinholeCamera, camera_pose, rot_z
from shared.schemas import Pose

needs_numba = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
KERNELS = [pytest.param("numba", marks=needs_numba), "numpy"]

CAM = PinholeCamera(48, 36, 90.0)
ROOM_LO, ROOM_HI = np.array([-2.0, -1.5, 0.0]), np.array([2.5, 1.8, 2.6])


def _frames(poses: list[np.ndarray], depth_of, cam: PinholeCamera = CAM) -> list[PosedImage]:
    """Frames of exact z-depth: ``depth_of(origin, world ray directions (H, W, 3))`` along unit-z rays."""
    rays = cam.pixel_rays()
    images = []
    for i, wfc in enumerate(poses):
        t = depth_of(wfc[:3, 3], rays @ wfc[:3, :3].T)
        rgb = np.full((cam.height_px, cam.width_px, 3), 40 * i % 256, np.uint8)
        images.append(PosedImage(rgb, wfc, cam, depth_m=t.astype(np.float32), index=i))
    return images


def _box_depth(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance (in units of the ray) to the walls, floor and ceiling of the box room, from inside."""
    with np.errstate(divide="ignore"):
        bound = np.where(dirs > 0, ROOM_HI, ROOM_LO)
        t = np.where(dirs != 0, (bound - origin) / dirs, np.inf)
    return t.min(axis=-1)


def _plane_depth(x_m: float):
    def depth(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (x_m - origin[0]) / dirs[..., 0]
        return np.where(np.isfinite(t) & (t > 0), t, 0.0)

    return depth


def _turning_region(headings_rad, floor_xy=(0.3, -0.2), pitch_rad=0.0) -> RegionInput:
    """A camera turning on the spot in the box room; the region starts there, heading 0."""
    pos = (*floor_xy, 0.0)
    poses = [camera_pose(pos, h, pitch_rad) for h in headings_rad]
    return RegionInput(0, Pose(position_m=pos, heading_rad=0.0), _frames(poses, _box_depth))


def _dots(cloud: PointCloud, centre: np.ndarray) -> np.ndarray:
    """Dot of each dequantised view direction with the true unit vector from the point to ``centre``."""
    true = centre - cloud.xyz.astype(np.float64)
    true /= np.linalg.norm(true, axis=1, keepdims=True)
    return (view_dirs_unit(cloud.view_dirs) * true).sum(axis=1)


@pytest.mark.parametrize("kernel", KERNELS)
def test_a_surface_seen_from_one_side_points_to_the_camera(kernel):
    region = _turning_region(np.linspace(0, 2 * np.pi, 8, endpoint=False), pitch_rad=-0.4)
    cloud = RECONSTRUCTORS.create("rgbd", {"kernel": kernel}).reconstruct(region).cloud
    assert cloud.view_dirs is not None and len(cloud) > 1000
    # The region's frame is the start pose's: the camera centre sits at (0, 0, h) in it.
    dots = _dots(cloud, np.array([0.0, 0.0, region.camera_height_m]))
    assert dots.min() > 0.9 and np.median(dots) > 0.99
    # Every wall appears: the directions are not one vector that happens to fit.
    assert np.ptp(cloud.view_dirs[:, :2].astype(int), axis=0).min() > 200


@pytest.mark.parametrize("kernel", KERNELS)
def test_a_thin_surface_seen_from_both_sides_has_a_short_view_vector(kernel):
    # The plane x = 2, seen by a camera at x = 0 looking +x and its mirror image at x = 4 looking -x:
    # each voxel holds as many points seen from either side, and their unit vectors' components
    # across the plane cancel; what is left, along it, is short near the cameras' axis.
    front, back = camera_pose((0.0, 0.0, 0.0), 0.0), camera_pose((4.0, 0.0, 0.0), np.pi)
    backend = RECONSTRUCTORS.create("rgbd", {"kernel": kernel, "remove_outliers": False, "voxel_m": 0.1})

    def cloud(poses):
        images = _frames(poses, _plane_depth(2.0), PinholeCamera(160, 120, 90.0))
        return backend.reconstruct(RegionInput(0, Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0), images)).cloud

    one = cloud([front])
    both = cloud([front, back])
    v_one, v_both = view_dirs_unit(one.view_dirs), view_dirs_unit(both.view_dirs)
    assert np.linalg.norm(v_one, axis=1).min() > 0.98
    assert v_one[:, 0].max() < -0.5  # towards x = 0, where the camera is
    assert np.array_equal(both.xyz, one.xyz)
    assert np.abs(v_both[:, 0]).max() < 0.05
    length_both = np.linalg.norm(v_both, axis=1)
    near_axis = np.linalg.norm(both.xyz[:, 1:] - [0.0, 1.25], axis=1) < 0.3
    assert near_axis.sum() > 10 and length_both[near_axis].max() < 0.2


def test_mono_sim_view_directions_turn_with_its_reference_camera():
    # The emulated monocular cloud sits in its reference camera's level frame, camera at the origin:
    # the view directions must point there, whichever of the turning frames was the reference.
    region = _turning_region(np.linspace(0, 2 * np.pi, 8, endpoint=False))
    regional = RECONSTRUCTORS.create("mono-sim", {"seed": 1, "noise_rel": 0.0}).reconstruct(region)
    assert abs(math.remainder(regional.true_yaw_rad, 2 * math.pi)) > 0.5  # forgetting the turn would fail
    dots = _dots(regional.cloud, np.zeros(3))
    assert np.median(dots) > 0.99 and (dots > 0.9).mean() > 0.99


def test_alignment_turns_view_directions_with_the_cloud():
    rng = np.random.default_rng(5)
    units = rng.normal(size=(200, 3))
    units /= np.linalg.norm(units, axis=1, keepdims=True)
    views = quantise_view_dirs(units)
    theta0, theta_t, delta = 0.9, 0.8, 2.0
    cloud = PointCloud(rng.normal(size=(200, 3)), np.zeros((200, 3), np.uint8), view_dirs=views)
    regional = RegionalCloud(0, cloud, False, np.zeros(3), "x", 1)
    report = AlignmentReport(0, 0, 1.0, theta_t, theta_t, delta, delta, delta, 1.0, 1, "sensor", 0, 0, 0)
    region = RegionInput(0, Pose(position_m=(3.0, -1.0, 0.0), heading_rad=theta0), [])
    out = to_world(regional, report, region)
    want = view_dirs_unit(views) @ rot_z(theta0 + theta_t).T
    # One requantisation: within half a step per component (and far from the unturned vectors).
    assert np.abs(view_dirs_unit(out.view_dirs) - want).max() <= 0.5 / 127 + 1e-6
    assert np.abs(view_dirs_unit(out.view_dirs) - view_dirs_unit(views)).max() > 0.5
    regional.cloud = PointCloud(cloud.xyz, cloud.rgb)
    assert to_world(regional, report, region).view_dirs is None


def test_voxel_merge_averages_view_directions_and_never_invents_them():
    xyz = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.51, 0.5, 0.5]])
    units = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    out = voxel_downsample(PointCloud(xyz, np.zeros((3, 3), np.uint8), view_dirs=quantise_view_dirs(units)), 0.1)
    order = np.argsort(out.xyz[:, 0])
    assert np.allclose(view_dirs_unit(out.view_dirs[order]), [[0.5, 0.5, 0], [0, 0, -1]], atol=1 / 127)
    assert voxel_downsample(PointCloud(xyz, np.zeros((3, 3), np.uint8)), 0.1).view_dirs is None
    # Batches with and without view vectors: the cloud has none, in either order, compacted or not.
    for first, second in ((units, None), (None, units)):
        acc = VoxelAccumulator(0.1)
        acc.add(xyz, np.zeros((3, 3), np.uint8), view_units=first)
        acc.add(xyz + 1.0, np.zeros((3, 3), np.uint8), view_units=second)
        assert acc.cloud().view_dirs is None and acc.voxel_count == 4
        assert acc.cloud().view_dirs is None
    # Sums merge across batches and compactions: 15 batches seen one way, 5 the opposite way.
    acc = VoxelAccumulator(0.1)
    for k in range(20):
        acc.add(xyz, np.zeros((3, 3), np.uint8), view_units=units if k % 4 else -units)
    out = acc.cloud()
    order = np.argsort(out.xyz[:, 0])
    assert np.allclose(view_dirs_unit(out.view_dirs[order]), [[0.25, 0.25, 0], [0, 0, -0.5]], atol=1 / 127)
