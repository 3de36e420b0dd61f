"""Pieces of the ros2 backend that need no robot: map geodesics, robot time, intrinsics resampling."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from libs.ros2 import messages as m
from services.robot_io.core.ros2.backend import RobotClock, _Latest, commanded_turn_rad
from libs.ros2.occupancy import OccupancyPlanner
from libs.ros2.profiles import profile


def _map_with_a_door():
    grid = np.zeros((40, 60), np.int8)  # 0.1 m cells: 6 m x 4 m
    grid[:, 30] = 100  # a wall at x = 3.0 m ...
    grid[30:34, 30] = 0  # ... with a door at y = 3.0-3.4 m
    return m.decode(m.MESSAGES["occupancy_grid"], m.encode(m.MESSAGES["occupancy_grid"],
                    m.occupancy_grid(0.0, "map", grid, 0.1, (0.0, 0.0))))


def test_geodesic_on_the_map_goes_through_the_door():
    planner = OccupancyPlanner.from_msg(_map_with_a_door())
    a, b = (1.05, 1.05, 0.0), (5.05, 1.05, 0.0)
    d = planner.distance(a, b)
    through_door = math.hypot(3.0 - 1.05, 3.2 - 1.05) + math.hypot(5.05 - 3.0, 3.2 - 1.05)
    assert through_door - 0.3 < d < through_door * 1.15
    path = planner.path(a, b)
    assert path is not None and np.min(np.abs(path[:, 0] - 3.05)) < 0.1
    assert np.any((np.abs(path[:, 0] - 3.05) < 0.06) & (path[:, 1] > 2.9) & (path[:, 1] < 3.5))


def test_a_robot_wider_than_the_door_has_no_path():
    planner = OccupancyPlanner.from_msg(_map_with_a_door(), robot_radius_m=0.3)
    assert math.isinf(planner.distance((1.05, 1.05, 0), (5.05, 1.05, 0)))
    assert planner.path((1.05, 1.05, 0), (5.05, 1.05, 0)) is None


def test_robot_time_is_the_clock_topic_without_extrapolation_and_silence_is_measured():
    c = RobotClock(use_clock=True)
    assert math.isnan(c.now()) and math.isinf(c.silence_s())
    t0 = time.monotonic()
    for k in range(30):  # a simulator at up to 4x real time (sleep() on a busy machine only slows it)
        if k in (0, 29):
            before = time.monotonic()
        c.on_clock(100.0 + 0.04 * k)
        if k == 0:
            first = (before, time.monotonic())
        elif k == 29:
            last = (before, time.monotonic())
        time.sleep(0.01)
    assert c.now() == 100.0 + 0.04 * 29
    # The rate is robot seconds over the wall seconds between the first and the last message, whatever
    # the machine's load made of the sleeps: the two wall readings bracket the clock's own.
    robot_span_s = 0.04 * 29
    assert robot_span_s / (last[1] - first[0]) <= c.rate <= robot_span_s / (last[0] - first[1])
    assert c.rate < 4.5
    time.sleep(0.05)
    assert c.now() == 100.0 + 0.04 * 29 and c.silence_s() >= 0.05
    assert time.monotonic() - t0 < 5
    wall = RobotClock(use_clock=False)
    assert abs(wall.now() - time.time()) < 0.1 and wall.silence_s() == 0.0 and wall.rate == 1.0


def test_a_teleport_waits_past_odometry_of_the_old_pose_that_was_still_in_flight():
    """The clock read after the teleport call can lag the odometry: a message of the old pose, stamped
    after that clock value, may arrive first (a CI run saw the old heading). The reset answers with the
    pose that shows the teleport."""
    import threading

    from services.robot_io.core.ros2.backend import Ros2Robot
    from shared.schemas import Pose

    class Teleport:
        def call(self, req, timeout_s):
            robot._odom.put(10.05, m.odometry(10.05, (2.0, 8.0, 0.0), 1.54, 0.0, 0.0, "odom", "base_link"))
            threading.Timer(0.1, lambda: robot._odom.put(
                10.10, m.odometry(10.10, (req.x, req.y, 0.0), req.theta, 0.0, 0.0, "odom", "base_link"))).start()
            return None

    robot = object.__new__(Ros2Robot)
    robot._teleport, robot._odom, robot.clock = Teleport(), _Latest(), RobotClock(use_clock=True)
    robot.profile = profile("generic")  # odometry is the world frame (no map_frame)
    robot._send_zero = lambda: None
    robot.clock.on_clock(10.0)
    got = robot.reset(Pose(position_m=(2.0, 8.0, 0.0), heading_rad=0.0))
    assert abs(got.heading_rad) < 1e-6 and got.position_m[:2] == (2.0, 8.0)


def test_a_simulator_whose_odometry_frame_is_not_the_teleports_gets_its_newest_odometry(monkeypatch):
    from services.robot_io.core.ros2 import backend
    from services.robot_io.core.ros2.backend import Ros2Robot
    from shared.schemas import Pose

    # The product's settle period (1 s) waited here would be idle time; the wait is the same code at 0.2 s.
    settle_s = 0.2
    monkeypatch.setattr(backend, "TELEPORT_SETTLE_S", settle_s)

    # Built before the clock starts: the first message built in a worker takes about 0.2 s, which would hide a
    # reset that returned at once.
    at_zero = m.odometry(10.05, (0.0, 0.0, 0.0), 0.0, 0.0, 0.0, "odom", "base_link")

    class Teleport:
        def call(self, req, timeout_s):  # odometry starts at zero wherever the robot is put
            robot._odom.put(10.05, at_zero)

    robot = object.__new__(Ros2Robot)
    robot._teleport, robot._odom, robot.clock = Teleport(), _Latest(), RobotClock(use_clock=True)
    robot.profile = profile("generic")  # odometry is the world frame (no map_frame)
    robot._send_zero = lambda: None
    robot.clock.on_clock(10.0)
    t0 = time.monotonic()
    got = robot.reset(Pose(position_m=(2.0, 8.0, 0.0), heading_rad=1.0))
    assert got.position_m[:2] == (0.0, 0.0)
    assert settle_s <= time.monotonic() - t0 < settle_s + 5.0


def test_the_localised_pose_composes_map_to_odom_with_odometry_and_ignores_the_rest_of_the_tree():
    from services.robot_io.core.ros2.backend import Ros2Robot, StaleDataError
    from shared.schemas import Pose

    robot = object.__new__(Ros2Robot)
    robot.profile = profile("generic", {"map_frame": "map"})
    robot._map_odom = _Latest()
    odo = Pose(position_m=(1.0, 0.0, 0.0), heading_rad=0.0)
    with pytest.raises(StaleDataError, match="map -> odom"):
        robot._world(odo)
    tf = m.transform_stamped
    # Only map -> odom is read (a leading slash is the same frame); a NaN transform is dropped.
    robot._on_tf(m.tf_message([tf(1.0, "odom", "base_link", (5.0, 5.0, 0.0), 1.0),
                               tf(1.0, "/map", "odom", (2.0, 3.0, 0.0), math.pi / 2)]), None)
    robot._on_tf(m.tf_message([tf(2.0, "map", "odom", (float("nan"), 0.0, 0.0), 0.0)]), None)
    robot._on_tf(m.tf_message([tf(3.0, "map", "camera_link", (9.0, 9.0, 0.0), 0.0)]), None)
    got = robot._world(odo)
    # Odometry (1, 0) heading 0, turned a quarter and shifted by (2, 3): (2, 4) heading 90 deg.
    assert np.allclose(got.position_m, (2.0, 4.0, 0.0), atol=1e-9)
    assert abs(got.heading_rad - math.pi / 2) < 1e-9
    # Without a localisation frame, odometry is the pose.
    robot.profile = profile("generic")
    assert robot._world(odo) == odo


def test_the_turn_commanded_since_a_stamp_counts_each_rate_until_the_next_command():
    sent = [(10.0, 0.2), (10.5, 0.4), (11.0, 0.0)]
    # Odometry stamped at 10.25 s, read at 11.5 s: 0.25 s at 0.2 rad/s, 0.5 s at 0.4, then at rest.
    assert commanded_turn_rad(sent, 10.25, 11.5) == pytest.approx(0.25 * 0.2 + 0.5 * 0.4)
    # Stamped before the turn began: all of it; the last rate holds until now.
    assert commanded_turn_rad(sent[:2], 9.0, 10.75) == pytest.approx(0.5 * 0.2 + 0.25 * 0.4)
    # Odometry newer than every command, and no commands yet: nothing ahead of it.
    assert commanded_turn_rad(sent, 11.2, 11.5) == 0.0
    assert commanded_turn_rad([], 0.0, 5.0) == 0.0
