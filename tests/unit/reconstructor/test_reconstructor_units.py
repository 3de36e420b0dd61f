"""Voxel fusion, frame validation, backend errors and the global integration formula."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.reconstructor.core import (
    METRIC_DEPTH,
    RECONSTRUCTORS,
    AlignmentReport,
    BackendUnavailableError,
    EmptyRecordingError,
    InputError,
    InvalidFrameError,
    MissingDepthError,
    RegionalCloud,
    RegionInput,
    ReconstructionConfig,
    Reconstructor,
    VoxelAccumulator,
    region_from_frames,
    to_world,
    voxel_downsample,
)
from shared.cloud import PointCloud
from shared.geometry import rot_z
from shared.registry import UnknownBackendError
from shared.schemas import CameraIntrinsics, Frame, Pose


def test_voxel_fusion_centroid_colour_and_majority_label():
    xyz = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.03, 0.01, 0.02], [0.51, 0.5, 0.5]])
    rgb = np.array([[0, 0, 0], [30, 60, 90], [60, 120, 180], [1, 2, 3]], np.uint8)
    labels = np.array([2, 5, 5, -1], np.int32)
    out = voxel_downsample(PointCloud(xyz, rgb, labels, {5: "sofa"}), 0.1)
    order = np.argsort(out.xyz[:, 0])
    assert len(out) == 2
    assert np.allclose(out.xyz[order[0]], xyz[:3].mean(axis=0), atol=1e-6)
    assert out.rgb[order[0]].tolist() == [30, 60, 90]
    assert out.labels[order].tolist() == [5, -1]  # majority; unknown only where nothing is known
    assert out.label_names == {5: "sofa"}


def test_voxel_accumulator_batches_equal_one_shot():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-2, 2, (20_000, 3))
    rgb = rng.integers(0, 256, (20_000, 3), dtype=np.uint8)
    lab = rng.integers(-1, 4, 20_000).astype(np.int32)
    one = voxel_downsample(PointCloud(xyz, rgb, lab), 0.25)
    acc = VoxelAccumulator(0.25)
    for k in range(0, 20_000, 700):  # many batches: exercises the periodic compaction too
        acc.add(xyz[k : k + 700], rgb[k : k + 700], lab[k : k + 700])
    many = acc.cloud()
    o1, o2 = np.lexsort(one.xyz.T), np.lexsort(many.xyz.T)
    assert np.allclose(one.xyz[o1], many.xyz[o2], atol=1e-5)
    assert np.array_equal(one.rgb[o1], many.rgb[o2]) and np.array_equal(one.labels[o1], many.labels[o2])
    assert acc.points_in == 20_000


def test_voxel_range_is_checked():
    with pytest.raises(InputError):
        voxel_downsample(PointCloud(np.array([[1e4, 0, 0]]), np.zeros((1, 3), np.uint8)), 0.03)


def _frame(index=0, depth=True, **pose_kw) -> Frame:
    cam = CameraIntrinsics(width_px=16, height_px=16, hfov_deg=90.0)
    return Frame(
        index=index, timestamp_s=0.0, pose=Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0),
        imu_heading_rad=0.0, camera=cam, rgb=np.zeros((16, 16, 3), np.uint8),
        depth_m=np.full((16, 16), 2.0, np.float32) if depth else None, **pose_kw,
    )


def test_bad_inputs_give_typed_errors():
    start = Pose(position_m=(0.0, 0.0, 0.0))
    with pytest.raises(EmptyRecordingError):
        region_from_frames(0, start, [])
    nan_pose = _frame().model_copy(update={"pose": Pose.model_construct(position_m=(math.nan, 0.0, 0.0), heading_rad=0.0)})
    with pytest.raises(InvalidFrameError):
        region_from_frames(0, start, [nan_pose])
    with pytest.raises(InvalidFrameError):
        # The schema now rejects it on construction; a producer using model_construct does not.
        region_from_frames(0, start, [_frame().model_copy(update={"pitch_rad": math.inf})])
    with pytest.raises(InvalidFrameError):
        region_from_frames(0, start, [_frame().model_copy(update={"depth_m": np.ones((8, 8), np.float32)})])
    no_depth = region_from_frames(0, start, [_frame(depth=False)])
    with pytest.raises(MissingDepthError):
        RECONSTRUCTORS.create("rgbd").reconstruct(no_depth)
    with pytest.raises(MissingDepthError):
        METRIC_DEPTH.create("sensor").depth(no_depth.images[0])
    holes = region_from_frames(0, start, [_frame().model_copy(update={"depth_m": np.zeros((16, 16), np.float32)})])
    with pytest.raises(EmptyRecordingError):
        RECONSTRUCTORS.create("rgbd").reconstruct(holes)
    with pytest.raises(EmptyRecordingError):
        Reconstructor().build([])
    # All of them are ValueErrors too, so the bus adapter can answer BAD_REQUEST for the family.
    assert issubclass(InvalidFrameError, ValueError)


def test_optional_backends_fail_clearly():
    with pytest.raises(BackendUnavailableError, match="weights"):
        RECONSTRUCTORS.create("mono")
    with pytest.raises(BackendUnavailableError, match="(transformers|cannot load)"):
        METRIC_DEPTH.create("depth-anything-v2")
    with pytest.raises(UnknownBackendError):
        Reconstructor(ReconstructionConfig(backend="nerf"))
    with pytest.raises(ValueError):
        RECONSTRUCTORS.create("rgbd", {"min_depth_m": 5.0, "max_depth_m": 1.0})


def test_global_integration_formula():
    # W_global = R_z(theta0 + theta_t) (delta (W - c) + (0, 0, h)) + p0, checked against a direct
    # construction: a point 2 m ahead of a camera at origin of a scaled, camera-centred frame.
    rng = np.random.default_rng(3)
    local = rng.normal(size=(50, 3))
    delta, theta0, theta_t, h = 2.5, 0.7, -0.3, 1.25
    p0 = np.array([3.0, -1.0, 2.5])
    regional = RegionalCloud(0, PointCloud(local, np.zeros((50, 3), np.uint8)), False, np.zeros(3), "x", 1)
    report = AlignmentReport(0, 0, 1.0, theta_t, theta_t, delta, delta, delta, 1.0, 1, "sensor", 0, 0, 0)
    region = RegionInput(0, Pose(position_m=tuple(p0), heading_rad=theta0), [], camera_height_m=h)
    out = to_world(regional, report, region).xyz
    want = (delta * local + [0, 0, h]) @ rot_z(theta0 + theta_t).T + p0
    assert np.allclose(out, want, atol=1e-4)
    # A metric cloud in the floor-point frame (camera at (0, 0, h)) is only rotated and moved.
    regional_m = RegionalCloud(0, PointCloud(local, np.zeros((50, 3), np.uint8)), True, np.array([0, 0, h]), "x", 1)
    report_m = AlignmentReport(0, 0, 1.0, 0.0, 0.0, 1.01, 1.0, 1.0, 1.0, 1, "sensor", 0, 0, 0)
    out_m = to_world(regional_m, report_m, region).xyz
    assert np.allclose(out_m, local @ rot_z(theta0).T + p0, atol=1e-4)
