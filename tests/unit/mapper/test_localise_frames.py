"""Tour frames registered between panoramas (localise.py, ``LocaliserConfig.frames``): a frame's
partial scan corrects the drift since the last panorama, exact poses stay exact, a featureless wall
keeps odometry along it, and a pitched frame only takes the correction in effect."""

from __future__ import annotations

import math

import numpy as np

from shared.geometry import PinholeCamera
from shared.schemas import Pose

from services.mapper.core.localise import (
    Correction, FrameRegistrationConfig, LocalisedRobot, Localiser, LocaliserConfig, frame_scan,
)
from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world
from tests.unit.mapper.test_localise import DriftingRobot, _error, corridor_world


CAMERA = PinholeCamera(128, 128, 90.0)  # the mapper's tour frames are 128 px wide


def _frames_on() -> LocaliserConfig:
    return LocaliserConfig(frames=FrameRegistrationConfig(enabled=True))  # off by default (see its config)


def _level_frame(robot: DriftingRobot):
    return robot.look_around()[0]  # (yaw 0, pitch 0): the view ahead


def test_a_frame_scan_lies_on_the_walls():
    """A level frame in the big room (walls at x=0, y=0, y=4 and x=6 but for its door) from (4, 1),
    looking 20 deg left of +x: its rays land on those walls, from the heading the frame reports."""
    robot = BoxWorldRobot(rooms_world(), CAMERA)
    robot.reset(Pose(position_m=(4.0, 1.0, 0.0), heading_rad=0.35))
    scan = frame_scan(robot.look_around()[0], LocaliserConfig())
    assert len(scan) > 60
    c, s = math.cos(0.35), math.sin(0.35)
    xy = scan[:, :2] @ np.array([[c, -s], [s, c]]).T + (4.0, 1.0)
    to_wall = np.min(np.abs(np.stack([xy[:, 0], xy[:, 1], xy[:, 1] - 3.95, xy[:, 0] - 5.95], axis=1)), axis=1)
    assert np.percentile(to_wall, 95) < 0.01


def test_a_frame_corrects_the_drift_since_the_last_panorama():
    """The start anchors the model; after a metre the odometry is 4 cm and 1.5 deg off: a level tour
    frame facing a corner, not a panorama, puts the correction within 1 cm and 0.3 deg of the truth."""
    robot = DriftingRobot(BoxWorldRobot(rooms_world(), CAMERA))
    robot.robot.reset(Pose(position_m=(2.0, 2.0, 0.0), heading_rad=0.3))
    loc = Localiser(_frames_on())
    lr = LocalisedRobot(robot, loc)
    lr.observe()
    lr.move_to(1.2, 0.5)
    # Facing the room's corner at the origin: two walls pin both directions (one wall would not).
    robot.robot.turn(math.remainder(-2.44 - robot.true_pose.heading_rad, 2 * math.pi))
    robot.offset = (0.03, -0.025, math.radians(1.5))
    before = _error(loc.correction.pose(robot.pose), robot.true_pose)
    frame = loc.localise_frame(_level_frame(robot))
    step = loc.frame_steps[-1]
    assert step.outcome == "corrected", step
    pos, head = _error(frame.pose, robot.true_pose)
    assert before[0] > 0.035 and pos < 0.01 and head < 0.3, (before, pos, head, step)
    assert len(loc.steps) == 1  # a frame is not a panorama: it adds nothing to the model
    assert loc.since_fix_m > 0.8 and loc.prior_sigma()[0] == loc.config.prior_m  # hubs still re-localise;
    # the prior narrows to what drifts from the placed frame on


def test_exact_frames_pass_through_unchanged():
    """An exact robot's level frames agree with odometry within the gate: each comes back as the very
    same object and the correction stays exactly zero."""
    robot = BoxWorldRobot(rooms_world(), CAMERA)
    robot.reset(Pose(position_m=(2.0, 2.0, 0.0), heading_rad=0.3))
    loc = Localiser(_frames_on())
    lr = LocalisedRobot(robot, loc)
    lr.observe()
    for dx, dy in ((0.5, 0.2), (0.7, 0.3), (0.0, 0.6), (-1.0, 0.2)):
        lr.move_to(dx, dy)
        for f in robot.look_around()[:3]:
            assert loc.localise_frame(f) is f
    assert loc.correction == Correction()
    assert any(s.outcome == "agrees" for s in loc.frame_steps)
    assert all(not s.outcome == "corrected" for s in loc.frame_steps)


def test_a_featureless_wall_does_not_fling_a_frame():
    """A frame that sees one flat corridor wall pins the robot across the wall, not along it: a
    30 cm drift along the wall is not 'corrected' (odometry kept along it), and a frame of the
    corridor's empty length moves nothing."""
    robot = DriftingRobot(BoxWorldRobot(corridor_world(), CAMERA))
    loc = Localiser(_frames_on())
    lr = LocalisedRobot(robot, loc)
    lr.observe()
    lr.move_to(1.0, 0.0)
    robot.offset = (0.3, 0.0, 0.0)
    robot.robot.turn(math.pi / 2)  # facing the wall y = 1.6 from 0.8 m
    loc.localise_frame(_level_frame(robot))
    assert abs(loc.correction.dx_m) < 0.01, (loc.correction, loc.frame_steps[-1])
    robot.robot.turn(-math.pi / 2)  # along the corridor: walls at a glancing angle, its end 19 m away
    loc.localise_frame(_level_frame(robot))
    assert abs(loc.correction.dx_m) < 0.01, (loc.correction, loc.frame_steps[-1])


def test_pitched_and_disabled_frames_only_take_the_correction():
    """A pitched frame (the height band assumes a level camera) and any frame with frame
    registration off are not registered: they take the correction in effect."""
    robot = DriftingRobot(BoxWorldRobot(rooms_world(), CAMERA))
    robot.robot.reset(Pose(position_m=(2.0, 2.0, 0.0), heading_rad=0.0))
    cfg = _frames_on()
    loc = Localiser(cfg)
    LocalisedRobot(robot, loc).observe()
    robot.offset = (0.03, 0.0, 0.0)
    pitched = robot.look_around()[3]
    assert pitched.pitch_rad != 0.0
    assert loc.localise_frame(pitched) is pitched and not loc.frame_steps
    cfg.frames.enabled = False
    level = _level_frame(robot)
    assert loc.localise_frame(level) is level and not loc.frame_steps


def test_a_band_chosen_by_the_column_reads_a_noisy_wall_without_bias():
    """Depth noise of 1 % x range^2 on a wall 2.9 m ahead, near the 3 m range cut: pixels picked into the band and
    the range cut by their own noisy depth read the wall short (the far-reading ones fall out at the
    band's edges and the cut); picked by their column's median range they do not."""
    robot = BoxWorldRobot(rooms_world(), CAMERA)
    robot.reset(Pose(position_m=(3.05, 1.0, 0.0), heading_rad=0.0))  # facing x = 5.95, 2.9 m off
    frame = robot.look_around()[0]
    rng = np.random.default_rng(3)
    bias = {}
    for by_median in (False, True):
        cfg = LocaliserConfig(band_from_median=by_median)
        xs = []
        for _ in range(20):
            d = np.asarray(frame.depth_m, np.float64)
            noisy = (d + rng.normal(0.0, 1.0, d.shape) * 0.01 * d**2).astype(np.float32)
            scan = frame_scan(frame.model_copy(update={"depth_m": np.maximum(noisy, 0.0)}), cfg)
            central = np.abs(scan[:, 1]) < 0.3  # the wall straight ahead (its door is further left)
            xs.append(scan[central, 0])
        bias[by_median] = float(np.mean(np.concatenate(xs)) - 2.9)
    assert bias[False] < -0.01, bias  # the pixel-by-pixel band: short by over a centimetre
    assert abs(bias[True]) < 0.4 * abs(bias[False]), bias
