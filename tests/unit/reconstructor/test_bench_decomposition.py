"""bench.anticipation --ladder --decompose: each oracle takes out exactly one error source of a noisy
robot's recording (issue 33), checked against the simulator itself."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench import agent_maps
from services.mapper.core.execute import RegionRecording
from services.robot_io.core import ROBOTS
from shared.schemas import Pose

SCENE = "generated:3:area=50"
CAM = {"width_px": 32, "height_px": 32}


@pytest.fixture(scope="module")
def recorded():
    """A noisy robot's frames with the simulator's truth of each, after a few drifting moves."""
    robot = ROBOTS.create("sim", {"scene": SCENE, "camera": CAM, "noise": agent_maps.noise_config("noisy", 4.0)})
    truth = agent_maps._recording_truth(robot)
    frames = []
    for k in range(4):
        robot.turn(0.8)
        robot.move_to(0.4 * math.cos(0.8 * (k + 1)), 0.4 * math.sin(0.8 * (k + 1)))
        frames.append(robot.render_frame(pitch_rad=0.1 * k))
    rec = RegionRecording(region=0, start_pose=frames[0].pose, frames=frames)
    yield robot, truth, rec
    robot.close()


def test_true_poses_keep_the_noisy_depth_and_put_every_frame_at_its_true_pose(recorded):
    robot, truth, rec = recorded
    assert any(f.pose != truth[f.index][0] for f in rec.frames)  # the odometry did drift
    out = agent_maps._oracle_frames([rec], truth, "true-poses", robot)[0]
    for f, g in zip(rec.frames, out.frames):
        assert g.pose == truth[f.index][0]
        assert np.array_equal(g.depth_m, f.depth_m) and g.depth_noise_rel == f.depth_noise_rel > 0
    assert out.start_pose == out.frames[0].pose


def test_exact_depth_is_what_an_exact_robot_sees_at_the_true_pose_and_the_frame_keeps_its_pose(recorded):
    robot, truth, rec = recorded
    out = agent_maps._oracle_frames([rec], truth, "exact-depth", robot)[0]
    exact = ROBOTS.create("sim", {"scene": SCENE, "camera": CAM})
    try:
        for f, g in zip(rec.frames, out.frames):
            true = truth[f.index][0]
            exact.reset(Pose(position_m=true.position_m, heading_rad=true.heading_rad))
            want = exact.render_frame(pitch_rad=f.pitch_rad).depth_m
            assert np.array_equal(g.depth_m, want) and not np.array_equal(g.depth_m, f.depth_m)
            assert g.depth_noise_rel == 0.0 and g.pose == f.pose and np.array_equal(g.rgb, f.rgb)
    finally:
        exact.close()
    assert out.start_pose == rec.start_pose


def test_the_route_oracle_takes_out_both_the_depth_noise_and_the_pose_error(recorded):
    robot, truth, rec = recorded
    out = agent_maps._oracle_frames([rec], truth, "route", robot)[0]
    depth = agent_maps._oracle_frames([rec], truth, "exact-depth", robot)[0]
    for f, g, e in zip(rec.frames, out.frames, depth.frames):
        assert g.pose == truth[f.index][0] and g.depth_noise_rel == 0.0
        assert np.array_equal(g.depth_m, e.depth_m) and np.array_equal(g.rgb, f.rgb)
    assert out.start_pose == out.frames[0].pose != rec.start_pose


def test_an_oracle_is_refused_for_an_exact_robot_or_by_an_unknown_name():
    with pytest.raises(ValueError):
        agent_maps.build_map(SCENE, "rgbd", None, frame_oracle="true-poses")
    with pytest.raises(ValueError):
        agent_maps.build_map(SCENE, "rgbd", "noisy", frame_oracle="exact-poses")
