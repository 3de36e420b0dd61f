"""The build job puts a recording's odometry frames in the map frame with the mapper's corrections
(issue 33): robot-io publishes frames past the mapper, with odometry poses, and the mapper sends its
map <- odom corrections beside the recording."""

from __future__ import annotations

import math

import numpy as np

from services.reconstructor.core.build_job import in_map_frame, with_odometry
from shared.schemas import (
    CameraIntrinsics, DriftCorrection, Frame, OdomCorrection, Pose, PoseGraphSummary, TourRecording,
)

CAM = CameraIntrinsics(width_px=8, height_px=8, hfov_deg=90.0)


def _frame(i: int, t: float, x: float, heading: float) -> Frame:
    return Frame(index=i, timestamp_s=t, pose=Pose(position_m=(x, 1.0, 0.0), heading_rad=heading),
                 imu_heading_rad=heading, camera=CAM, rgb=np.zeros((8, 8, 3), np.uint8))


def _recording(corrections: list[OdomCorrection]) -> TourRecording:
    return TourRecording(exploration_id="x1", recording="x1-r0", region=0, frame_count=4,
                         start_pose=Pose(position_m=(0.0, 1.0, 0.0), heading_rad=3.1), odom_corrections=corrections)


def test_each_frame_takes_the_correction_in_effect_at_its_time():
    first = OdomCorrection(since_s=1.0, dx_m=0.1, dy_m=-0.2, dyaw_rad=0.05)
    second = OdomCorrection(since_s=3.0, dx_m=-0.3, dy_m=0.0, dyaw_rad=-0.1)
    frames = [_frame(0, 0.5, 0.0, 3.1), _frame(1, 1.0, 1.0, 0.0), _frame(2, 2.9, 2.0, 0.0), _frame(3, 3.5, 3.0, 0.0)]
    # Given out of order: the build sorts them by time.
    start, fixed = in_map_frame(_recording([second, first]), frames)
    assert start.position_m == (0.1, 0.8, 0.0)
    # 3.1 + 0.05 wraps past pi.
    assert math.isclose(start.heading_rad, 3.15 - 2 * math.pi, abs_tol=1e-12)
    want = [first, first, first, second]  # a frame before the first correction takes the first
    for f, g, c in zip(frames, fixed, want):
        assert g.index == f.index and g.timestamp_s == f.timestamp_s and g.rgb is f.rgb
        assert np.allclose(g.pose.position_m, (f.pose.position_m[0] + c.dx_m, f.pose.position_m[1] + c.dy_m, 0.0))
        assert math.isclose(math.remainder(g.pose.heading_rad - f.pose.heading_rad - c.dyaw_rad, 2 * math.pi), 0.0,
                            abs_tol=1e-12)
        assert math.isclose(math.remainder(g.imu_heading_rad - f.imu_heading_rad - c.dyaw_rad, 2 * math.pi), 0.0,
                            abs_tol=1e-12)
    assert frames[1].pose.position_m == (1.0, 1.0, 0.0)  # the frames given are not changed


def test_a_recording_without_corrections_is_built_exactly_as_it_came():
    frames = [_frame(0, 0.5, 0.0, 0.2), _frame(1, 1.0, 1.0, 0.0)]
    rec = _recording([])
    start, same = in_map_frame(rec, frames)
    assert start is rec.start_pose and same is frames


def test_the_map_records_the_mappers_corrections_per_tour():
    """A robot without a localiser is corrected by the mapper's corrections first: the map's drift record
    says how many tours they moved and how far (the largest in effect during each tour)."""
    tours = [_recording([OdomCorrection(since_s=0.0, dx_m=0.3, dy_m=0.4, dyaw_rad=0.0),
                         OdomCorrection(since_s=5.0, dx_m=0.06, dy_m=0.08, dyaw_rad=-0.1)]),
             _recording([OdomCorrection(since_s=9.0, dx_m=0.0, dy_m=0.1, dyaw_rad=0.02)]),
             _recording([OdomCorrection(since_s=0.0, dx_m=0.0, dy_m=0.0, dyaw_rad=0.0)]),  # exact: not moved
             _recording([])]
    base = DriftCorrection(applied=False, regions_corrected=2, max_correction_m=0.02)
    d = with_odometry(base, tours)
    assert d.applied and d.odom_regions_corrected == 2
    assert math.isclose(d.odom_max_correction_m, 0.5) and math.isclose(d.odom_median_correction_m, 0.3)
    assert math.isclose(d.odom_max_correction_deg, math.degrees(0.1))
    assert d.regions_corrected == 2 and d.max_correction_m == 0.02  # the registration's record is kept
    # No correction at all (an exact robot, or a mapper that localised nothing): the record as it was.
    assert with_odometry(base, tours[2:]) is base
    # The mapper's pose graph goes into the record as it came (an exact robot's says it moved nothing).
    g = PoseGraphSummary(panoramas=12, scan_edges=30, loop_closures_accepted=20, loop_closures_rejected=1,
                         applied=True, panoramas_corrected=11, max_correction_m=0.2)
    assert with_odometry(base, tours, g).pose_graph == g
    assert with_odometry(base, tours[2:], g).pose_graph == g and not with_odometry(base, tours[2:], g).applied


def test_interpolated_corrections_grow_between_their_panoramas():
    """The mapper's pose graph placed each correction's panorama: a frame between two takes the
    correction interpolated in time (the drift grows on the way), one outside them the nearest."""
    first = OdomCorrection(since_s=1.0, dx_m=0.1, dy_m=-0.2, dyaw_rad=0.05)
    second = OdomCorrection(since_s=3.0, dx_m=-0.3, dy_m=0.0, dyaw_rad=-0.1)
    rec = _recording([second, first]).model_copy(update={"odom_corrections_interpolated": True})
    frames = [_frame(0, 0.5, 0.0, 0.0), _frame(1, 2.0, 1.0, 0.0), _frame(2, 2.5, 2.0, 0.0), _frame(3, 3.5, 3.0, 0.0)]
    start, fixed = in_map_frame(rec, frames)
    want = [(0.1, -0.2, 0.05), (-0.1, -0.1, -0.025), (-0.2, -0.05, -0.0625), (-0.3, 0.0, -0.1)]
    for f, g, (dx, dy, dyaw) in zip(frames, fixed, want):
        assert np.allclose(g.pose.position_m, (f.pose.position_m[0] + dx, f.pose.position_m[1] + dy, 0.0))
        assert math.isclose(g.pose.heading_rad, dyaw, abs_tol=1e-12)
        assert math.isclose(g.imu_heading_rad, dyaw, abs_tol=1e-12)
    assert start.position_m == (0.1, 0.8, 0.0)  # the start pose takes the first, as before
