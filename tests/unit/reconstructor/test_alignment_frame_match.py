"""Metric alignment when SSIM cannot tell the start frames apart (issue 20 item 7).

The condition of the outlier region of ``generated:1:area=60`` under mono-sim (10.3 % scale error):
the forward render shows a plain wall, frames 15 deg apart tie on SSIM, and the first of them, turned
away from the render, measures other surfaces. Here: a plain grey box room, ray-cast exactly, the
mono-sim cloud anchored to a frame at 15 deg, the frame at 0 deg listed first.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.reconstructor.core.align import AlignmentConfig, MetricAligner
from services.reconstructor.core.depth import SensorDepth
from services.reconstructor.core.frames import PosedImage, RegionInput
from services.reconstructor.core.regional import RegionalCloud
from shared.cloud import PointCloud
from shared.geometry import PinholeCamera, camera_pose, rot_z
from shared.schemas import Pose

H_M = 1.25  # camera height
ROOM = {"x": (-1.0, 1.2), "y": (-0.5, 4.0), "z": (0.0, 2.5)}  # a wall 1.2 m ahead, a long room to the left
GREY = 128


def _depth(world_from_camera: np.ndarray, cam: PinholeCamera) -> np.ndarray:
    """Exact z-depth of the box room's walls, floor and ceiling."""
    u, v = np.meshgrid(np.arange(cam.width_px) + 0.5, np.arange(cam.height_px) + 0.5)
    d_cam = np.stack([(u - cam.width_px / 2) / cam.fx, (v - cam.height_px / 2) / cam.fx, np.ones_like(u)], -1)
    d = d_cam @ world_from_camera[:3, :3].T  # per unit of z-depth
    c = world_from_camera[:3, 3]
    t = np.full(d.shape[:2], np.inf)
    for axis, (lo, hi) in enumerate(ROOM.values()):
        with np.errstate(divide="ignore", invalid="ignore"):
            for plane in (lo, hi):
                ti = (plane - c[axis]) / d[..., axis]
                t = np.where((ti > 1e-6) & (ti < t), ti, t)
    return t.astype(np.float32)


def _room_points(spacing_m: float = 0.03) -> np.ndarray:
    pts = []
    for axis, (lo, hi) in enumerate(ROOM.values()):
        others = [k for k in range(3) if k != axis]
        ranges = [np.arange(*list(ROOM.values())[k], spacing_m) for k in others]
        a, b = np.meshgrid(*ranges, indexing="ij")
        for plane in (lo, hi):
            p = np.zeros((a.size, 3))
            p[:, axis], p[:, others[0]], p[:, others[1]] = plane, a.ravel(), b.ravel()
            pts.append(p)
    return np.concatenate(pts)


@pytest.fixture(scope="module")
def tied_region():
    cam = PinholeCamera(64, 64, 90.0)
    headings = [0.0, math.radians(15), math.radians(30)]  # the reference frame is the second
    images = []
    for k, h in enumerate(headings):
        t = camera_pose((0.0, 0.0, 0.0), h, 0.0, H_M)
        rgb = np.full((cam.height_px, cam.width_px, 3), GREY, np.uint8)  # plain walls: SSIM ties
        images.append(PosedImage(rgb=rgb, world_from_camera=t, camera=cam, depth_m=_depth(t, cam), index=k,
                                 heading_rad=h, imu_heading_rad=h))
    region = RegionInput(0, Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0), images, camera_height_m=H_M)
    # What mono-sim hands over: the cloud in the reference camera's level frame, at an unknown scale.
    yaw, scale = headings[1], 1.7
    xyz = (_room_points() - [0.0, 0.0, H_M]) @ rot_z(yaw)
    rgb = np.full((len(xyz), 3), GREY, np.uint8)
    regional = RegionalCloud(region=0, cloud=PointCloud(xyz * scale, rgb), metric=False, camera_origin_m=np.zeros(3),
                             backend="test", frames_used=len(images), true_scale=scale, true_yaw_rad=yaw)
    return region, regional


def _scale_error(report, regional) -> float:
    return abs(report.delta_applied * regional.true_scale - 1.0)


def test_ssim_alone_takes_the_first_of_tied_frames_and_misses_the_scale(tied_region):
    region, regional = tied_region
    rep = MetricAligner(AlignmentConfig(verify_top_k=1), SensorDepth()).align(region, regional)
    assert rep.matched_index == 0  # the tie goes to the first frame, 15 deg off the reference
    assert _scale_error(rep, regional) > 0.05  # 11 % here, 10.3 % on the real region


def test_the_ratio_spread_picks_the_reference_frame_among_tied_ones(tied_region):
    region, regional = tied_region
    rep = MetricAligner(AlignmentConfig(), SensorDepth()).align(region, regional)
    assert rep.matched_index == 1
    assert rep.verified == 3
    assert rep.ratio_spread < 0.01
    assert _scale_error(rep, regional) <= 0.02
    assert rep.theta_t_rad == pytest.approx(math.radians(15))


def test_repeated_views_are_checked_once(tied_region):
    region, regional = tied_region
    twice = RegionInput(0, region.start_pose, [*region.images, *region.images], camera_height_m=H_M)
    rep = MetricAligner(AlignmentConfig(), SensorDepth()).align(twice, regional)
    assert rep.verified == 3 and rep.candidates == 6
    assert rep.matched_index == 1
