"""ROS 2 action types and keys (pure: no zenoh): the CDR types of NavigateToPose, Spin and CancelGoal,
their RIHS01 hashes as rosidl computes them, the rmw_zenoh keys of an action's five parts, and how
Nav2's result codes become our outcomes."""

from __future__ import annotations

import uuid

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from libs.ros2 import messages as m
from libs.ros2.action import ACTION_PARTS, GoalStatus, _default, action_names, duration, duration_s
from libs.ros2.keys import BridgeKeys, RmwZenohKeys
from services.robot_io.core.ros2.backend import NAV2_ERROR_OUTCOMES, Nav2Outcome, nav2_outcome

# Hashes of Jazzy's example_interfaces/action/Fibonacci parts and action_msgs' CancelGoal request and
# GoalStatusArray as an independent rmw_zenoh codec (a Swift one, found by search) asserts them in its
# tests; computed here by our own action_types() from the .action text.
INDEPENDENT_HASHES = {
    "example_interfaces/action/Fibonacci_SendGoal_Request":
        "RIHS01_3d088942b413247db536576f0286768c6be8fcd5d0c9a5d544f359fba090a238",
    "example_interfaces/action/Fibonacci_FeedbackMessage":
        "RIHS01_c1de71afd52e49a89c53d8262366884185bc0a02f78ce051c4e46b0a7fe59bb2",
    "action_msgs/srv/CancelGoal_Request": "RIHS01_3d3c84653c1f96918086887e1dcb236faec88b81a5b14fd4cf4840065bcdf8af",
    "action_msgs/msg/GoalStatusArray": "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e",
}


def test_action_type_hashes_match_an_independent_codec():
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(m.action_types("example_interfaces/action/Fibonacci", "int32 order\n", "int32[] sequence\n",
                                  "int32[] sequence\n"))
    store.register(m.service_types("action_msgs/srv/CancelGoal", *m.SERVICES["action_msgs/srv/CancelGoal"]))
    m._fix_char_arrays(store)
    for name, want in INDEPENDENT_HASHES.items():
        assert store.hash_rihs01(name) == want, name
    # Ours come from the same code path: the process typestore has them.
    assert m.type_hash("action_msgs/msg/GoalStatusArray") == INDEPENDENT_HASHES["action_msgs/msg/GoalStatusArray"]


def test_action_keys_in_both_styles():
    names = action_names("/navigate_to_pose")
    assert list(names) == list(ACTION_PARTS)
    assert names["send_goal"] == "/navigate_to_pose/_action/send_goal"
    send = m.RosType("nav2_msgs/action/NavigateToPose_SendGoal")
    assert send.is_service and not m.RosType("nav2_msgs/action/NavigateToPose_FeedbackMessage").is_service
    # rmw_zenoh names a service by its response type less "Response_" (rmw_service_data.cpp) and hashes
    # the service type: the action's generated services are services like any other.
    assert RmwZenohKeys().service_key(names["send_goal"], send) == (
        f"0/navigate_to_pose/_action/send_goal/nav2_msgs::action::dds_::NavigateToPose_SendGoal_/{send.type_hash}")
    status = m.RosType("action_msgs/msg/GoalStatusArray")
    assert RmwZenohKeys(domain_id=3).topic_key(names["status"], status).startswith(
        "3/navigate_to_pose/_action/status/action_msgs::msg::dds_::GoalStatusArray_/RIHS01_6c1684b0")
    assert BridgeKeys(prefix="robot").topic_key(names["cancel_goal"], None) == "robot/navigate_to_pose/_action/cancel_goal"


def test_navigate_to_pose_messages_roundtrip():
    gid = uuid.uuid4().bytes
    goal = m.new("nav2_msgs/action/NavigateToPose_Goal", pose=m.new(
        "geometry_msgs/msg/PoseStamped", header=m.header(0.0, "map"), pose=m.new(
            "geometry_msgs/msg/Pose", position=m.new("geometry_msgs/msg/Point", x=1.5, y=-2.0, z=0.0),
            orientation=m.quaternion_from_yaw(0.5))), behavior_tree="")
    req = m.new("nav2_msgs/action/NavigateToPose_SendGoal_Request",
                goal_id=m.new("unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(gid, np.uint8).copy()), goal=goal)
    back = m.decode("nav2_msgs/action/NavigateToPose_SendGoal_Request",
                    m.encode("nav2_msgs/action/NavigateToPose_SendGoal_Request", req))
    assert bytes(bytearray(back.goal_id.uuid)) == gid
    assert back.goal.pose.pose.position.x == 1.5 and back.goal.pose.header.frame_id == "map"
    assert abs(m.yaw_from_quaternion(back.goal.pose.pose.orientation) - 0.5) < 1e-9
    res = m.new("nav2_msgs/action/NavigateToPose_GetResult_Response", status=int(GoalStatus.ABORTED),
                result=m.new("nav2_msgs/action/NavigateToPose_Result", error_code=208, error_msg="no path"))
    back = m.decode("nav2_msgs/action/NavigateToPose_GetResult_Response",
                    m.encode("nav2_msgs/action/NavigateToPose_GetResult_Response", res))
    assert back.status == 6 and back.result.error_code == 208 and back.result.error_msg == "no path"
    # A result nobody filled encodes (a server answering an unknown goal sends one).
    assert m.encode("nav2_msgs/action/Spin_Result", _default("nav2_msgs/action/Spin_Result"))


def test_duration_roundtrip():
    assert duration_s(duration(12.25)) == pytest.approx(12.25)
    assert duration_s(duration(-3.0)) == 0.0


@pytest.mark.parametrize("code, outcome", [
    (105, Nav2Outcome.BLOCKED), (104, Nav2Outcome.BLOCKED), (703, Nav2Outcome.BLOCKED),
    (206, Nav2Outcome.UNREACHABLE), (208, Nav2Outcome.UNREACHABLE), (204, Nav2Outcome.UNREACHABLE),
    (107, Nav2Outcome.TIMEOUT), (701, Nav2Outcome.TIMEOUT),
    (102, Nav2Outcome.FAULT), (201, Nav2Outcome.FAULT),
    (0, Nav2Outcome.BLOCKED), (200, Nav2Outcome.BLOCKED), (12345, Nav2Outcome.BLOCKED),
])
def test_nav2_error_codes_map_to_our_outcomes(code, outcome):
    assert nav2_outcome(code) == outcome


def test_outcome_table_is_data_over_nav2_code_ranges():
    # Controller 10x, planner 20x, spin 70x, NavigateToPose's own 900x: nothing else sneaks in.
    assert all(c // 100 in (1, 2, 7) or 9000 <= c < 9100 for c in NAV2_ERROR_OUTCOMES)
