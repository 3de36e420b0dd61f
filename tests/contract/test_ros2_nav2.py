"""The ``ros2`` backend's Nav2 motion against the ROS 2 stand-in's Nav2 actions, over real zenoh
sessions on loopback, in both key styles.

The stand-in serves NavigateToPose (planning on its navigation grid) and Spin as bt_navigator and
behavior_server do; the backend sends goals, follows feedback and status, cancels on its deadline or a
halt, and maps Nav2's result codes to its outcomes. A third session, a plain action client, checks
the server side on its own (cancel mid-goal). Every wait is bounded; the checks are on state.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from libs.ros2 import messages as msgs
from libs.ros2.action import ActionClient, CancelReturn, GoalStatus
from libs.ros2.keys import key_style
from libs.ros2.node import Ros2Node
from services.robot_io.core.ros2.backend import DeadlineExceededError, RunStoppedError
from shared.schemas import MoveStatus
# The module's stand-ins (one per key style, reset by teleport) are test_ros2_backend's fixtures.
from tests.contract.test_ros2_backend import SIM_OVERRIDES, StandIn, standin, standins, transport  # noqa: F401
from tests.waiting import wait_until

pytestmark = pytest.mark.contract

NAV2 = {**SIM_OVERRIDES, "motion": "nav2"}


def goal_offset(s: StandIn, lo_m: float, hi_m: float, seed: int = 1) -> np.ndarray:
    """A walkable point whose path from the robot is between lo and hi metres, as an offset."""
    nav, here = s.robot.sim.nav, np.asarray(s.robot.true_pose.position_m)
    rng = np.random.default_rng(seed)
    for _ in range(2000):
        q = nav.sample_navigable(rng)
        # Distance from q to here: one shortest-path field (the goal's, here) serves every sample.
        if lo_m <= nav.geodesic_distance(q, here) <= hi_m and np.linalg.norm(q[:2] - here[:2]) >= 0.5 * lo_m:
            return q[:2] - here[:2]
    raise AssertionError(f"no walkable point {lo_m}-{hi_m} m away")


def ticks_pass(s: StandIn, n: int) -> None:
    """Wait until the stand-in has simulated ``n`` more control periods."""
    t0 = s.robot.stats.ticks
    wait_until(lambda: s.robot.stats.ticks >= t0 + n, 60, f"{n} stand-in ticks")


def nav_goals(s: StandIn):
    return list(s.robot._nav_server._goals.values())


def test_a_goal_reaches_its_pose_through_navigate_to_pose_with_feedback(standin):
    off = goal_offset(standin, 1.5, 3.0)
    start = np.asarray(standin.robot.true_pose.position_m[:2])
    with standin.backend(keys=standin.keys, overrides=NAV2) as robot:
        assert robot.motion_backends["move_to"] == "nav2" and robot.motion_backends["turn"] == "nav2"
        res = robot.move_to(*off)
        assert res.status == MoveStatus.REACHED, res
        assert np.linalg.norm(np.asarray(standin.robot.true_pose.position_m[:2]) - (start + off)) < 0.15
        assert res.travelled_m >= 0.9 * np.linalg.norm(off)
        goal = robot.nav2_last_goal
        assert goal.status == GoalStatus.SUCCEEDED and goal.feedback_count >= 3
        fb = goal.feedback
        assert math.isfinite(fb.distance_remaining) and fb.distance_remaining < 0.5
        assert fb.current_pose.header.frame_id == "odom" and fb.navigation_time.sec + fb.navigation_time.nanosec > 0
    # Nav2 drove the base, not our cmd_vel loop: nothing but zero Twists came from us.
    assert standin.robot.stats.nonzero_cmd == 0
    assert [g.status for g in nav_goals(standin)][-1] == GoalStatus.SUCCEEDED


def test_spin_turns_the_base(standin):
    with standin.backend(keys=standin.keys, overrides=NAV2) as robot:
        h0 = robot.pose.heading_rad
        pose = robot.turn(math.radians(100))
        assert abs(math.remainder(pose.heading_rad - h0 - math.radians(100), 2 * math.pi)) < math.radians(2)
        assert robot.nav2_last_goal.status == GoalStatus.SUCCEEDED
        assert robot.nav2_last_goal.result.total_elapsed_time.sec >= 0
    assert standin.robot.stats.nonzero_cmd == 0  # the Spin behaviour turned it


def test_an_unreachable_goal_is_a_typed_outcome_and_the_robot_stays(standin):
    with standin.backend(keys=standin.keys, overrides=NAV2) as robot:
        before = np.asarray(standin.robot.true_pose.position_m)
        res = robot.move_to(19.0, 0.0)  # far outside the house: in no free space
        assert res.status == MoveStatus.UNREACHABLE and res.travelled_m == 0.0 and res.steps == 0
        assert robot.nav2_last_goal.status == GoalStatus.ABORTED
        assert robot.nav2_last_goal.result.error_code == 206  # ComputePathToPose GOAL_OCCUPIED
    assert np.allclose(standin.robot.true_pose.position_m, before)


def test_a_cancel_mid_goal_stops_the_robot(standin):
    """A plain action client (not the backend) against the stand-in's server: cancel while driving."""
    t = transport(connect=[standin.endpoint])
    node = Ros2Node(t, key_style(standin.keys), "nav_client")
    try:
        client = ActionClient(node, "/navigate_to_pose", "nav2_msgs/action/NavigateToPose")
        wait_until(lambda: client.server_present(1.0), 30, "the NavigateToPose server")
        off = goal_offset(standin, 4.0, 8.0, seed=2)
        odo = standin.robot.odometry_pose()
        x, y = odo.position_m[0] + off[0], odo.position_m[1] + off[1]
        goal = msgs.new("nav2_msgs/action/NavigateToPose_Goal", behavior_tree="", pose=msgs.new(
            "geometry_msgs/msg/PoseStamped", header=msgs.header(0.0, "odom"), pose=msgs.new(
                "geometry_msgs/msg/Pose", position=msgs.new("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
                orientation=msgs.quaternion_from_yaw(0.0))))
        start = np.asarray(standin.robot.true_pose.position_m)
        handle = client.send_goal(goal)
        wait_until(lambda: handle.feedback_count >= 3
                   and np.linalg.norm(np.asarray(standin.robot.true_pose.position_m) - start) > 0.3, 60,
                   "the robot on its way")
        assert handle.status == GoalStatus.EXECUTING
        assert client.cancel(handle) == CancelReturn.NONE
        assert handle.wait(30) and handle.status == GoalStatus.CANCELED
        stopped = standin.robot.true_pose.position_m
        ticks_pass(standin, 60)  # two simulated seconds later it has not moved
        assert np.allclose(standin.robot.true_pose.position_m, stopped)
        assert np.linalg.norm(np.asarray(stopped) - start) < np.linalg.norm(off) - 0.5  # stopped short
        assert client.cancel(handle) == CancelReturn.GOAL_TERMINATED
    finally:
        node.close()
        t.close()


def test_our_deadline_cancels_the_goal(standins):
    s = standins("bridge")
    off = goal_offset(s, 4.0, 8.0, seed=3)
    with s.backend(keys="bridge", overrides=NAV2, command_deadline_s=1.5) as robot:
        with pytest.raises(DeadlineExceededError):
            robot.move_to(*off)
        assert robot.nav2_cancels == 1 and robot.nav2_last_goal.status == GoalStatus.CANCELED
        assert [g.status for g in nav_goals(s)][-1] == GoalStatus.CANCELED
        stopped = s.robot.true_pose.position_m
        ticks_pass(s, 60)
        assert np.allclose(s.robot.true_pose.position_m, stopped)


def test_a_halt_cancels_the_goal(standins):
    s = standins("rmw_zenoh")
    off = goal_offset(s, 4.0, 8.0, seed=4)
    with s.backend(keys="rmw_zenoh", overrides=NAV2) as robot:
        errors: list[BaseException] = []

        def drive():
            try:
                robot.move_to(*off)
            except BaseException as exc:  # noqa: BLE001 - the test reads it
                errors.append(exc)

        th = threading.Thread(target=drive)
        th.start()
        wait_until(lambda: robot.nav2_last_goal is not None and robot.nav2_last_goal.feedback_count >= 3, 60,
                   "the goal under way")
        robot.halt()
        th.join(60)
        assert not th.is_alive() and len(errors) == 1 and isinstance(errors[0], RunStoppedError)
        assert robot.nav2_last_goal.status == GoalStatus.CANCELED and robot.nav2_cancels == 1
        robot.clear_safety_stop()


def test_without_an_action_server_motion_falls_back_to_cmd_vel():
    s = StandIn(keys="bridge", nav2_actions=False, fast=True)
    try:
        off = goal_offset(s, 0.8, 1.2)
        with s.backend(keys="bridge", overrides=NAV2, nav2_probe_timeout_s=1.0) as robot:
            assert robot.motion_backends == {"move_to": "cmdvel", "turn": "cmdvel", "look_around": "cmdvel",
                                             "observe": "cmdvel"}
            res = robot.move_to(*off)
            assert res.status in (MoveStatus.REACHED, MoveStatus.BLOCKED) and res.travelled_m > 0.2
            assert robot.nav2_last_goal is None
        assert s.robot.stats.nonzero_cmd > 10  # our cmd_vel loop drove it
    finally:
        s.close()
