"""The whole method through the ROS 2 stand-in with Nav2 motion (``make demo ROBOT=ros2 ROS2_MOTION=nav2``):
every move a NavigateToPose goal and every turn a Spin goal to the stand-in's Nav2 actions.

One key style (bridge; the cmd_vel demo test runs rmw_zenoh, and tests/contract/test_ros2_nav2.py runs
the actions in both), on the cmd_vel test's small house, budget and time scale.
"""

from __future__ import annotations

import re

import pytest

from deploy.demo import main as demo_main
from tests.e2e.test_ros2_demo import FRAMES_TIMEOUT_S, SCENE, STANDIN

# slow: a whole ROS 2 demo (about 1.5-3.5 min on 2 cores) on top of the cmd_vel one that `make test` runs;
# the Nav2 actions themselves run in both key styles in `make test` (tests/contract/test_ros2_nav2.py).
# This one runs in `make reliability` (every tier, slow included).
pytestmark = [pytest.mark.e2e, pytest.mark.system, pytest.mark.slow]


def test_the_demo_runs_through_nav2_actions(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("ANT_FRAMES_TIMEOUT_S", FRAMES_TIMEOUT_S)
    code = demo_main(["--robot", "ros2", "--ros2-keys", "bridge", "--ros2-motion", "nav2", "--scene", SCENE,
                      "--run-dir", str(tmp_path), "--max-steps", "6", "--time-scale", "8", "--mission-steps", "3",
                      "--policy", "oracle", "--standin-config", STANDIN])
    out = capsys.readouterr().out
    assert code == 0, out[-3000:]
    assert "the ROS 2 backend ('ros2', bridge keys) with nav2 motion" in out
    result = next(line for line in out.splitlines() if "RESULT: " in line)
    assert "map demo-house v1" in out and "RESULT: mission " not in result and "ne_m=" in result, result
    # robot-io found both action servers and never fell back to cmd_vel for them.
    robot_io = (tmp_path / "logs" / "robot_io-0.log").read_text()
    assert "/navigate_to_pose (nav2_msgs/action/NavigateToPose) answers" in robot_io
    assert "/spin (nav2_msgs/action/Spin) answers" in robot_io and "that motion uses cmd_vel" not in robot_io
    # The stand-in ran the moves as Nav2 goals, and they got somewhere.
    stopped = next(line for line in (tmp_path / "logs" / "ros2-robot.log").read_text().splitlines()
                   if "stopped after" in line)
    reached = re.search(r"navigate_to_pose SUCCEEDED (\d+)", stopped)
    assert reached and int(reached.group(1)) >= 3, stopped
