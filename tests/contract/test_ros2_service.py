"""robot-io as a process with the ros2 backend: SIGTERM in the middle of a motion stops the robot
(the last Twist the robot's driver receives is zero) and the service exits cleanly."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading

import pytest

from libs.ros2.profiles import profile
from shared.bus.config import ZenohSettings
from shared.bus.typed import TypedBus
from shared.bus.zenoh_bus import ZenohBus
from shared.clients import RobotClient
from tests.contract.test_ros2_backend import SIM_OVERRIDES, CmdLog, StandIn
from tests.waiting import wait_until

pytestmark = [pytest.mark.contract, pytest.mark.system]  # robot-io as its own process


def test_sigterm_during_a_turn_sends_a_zero_twist_and_the_service_exits_cleanly():
    s = StandIn(keys="rmw_zenoh")
    log = CmdLog(s.endpoint, "rmw_zenoh", profile("generic", SIM_OVERRIDES).cmd_vel)
    config = {"keys": "rmw_zenoh", "profile_overrides": SIM_OVERRIDES, "max_data_age_s": 2.0, "connect_timeout_s": 60,
              "transport_config": {"zenoh": {"connect": [s.endpoint]}}}
    env = {**os.environ, "PYTHONPATH": os.getcwd(), "ANT_ROBOT_BACKEND": "ros2", "ANT_ROBOT_CONFIG": json.dumps(config),
           "ANT_ZENOH__CONNECT": json.dumps([s.endpoint]), "ANT_ZENOH__MULTICAST_SCOUTING": "false",
           "ANT_INSTANCE": "robot-io-ros2", "ANT_ROBOT": "r2"}
    proc = subprocess.Popen([sys.executable, "-m", "services.robot_io"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    bus = ZenohBus(ZenohSettings(connect=[s.endpoint]))
    try:
        wait_until(lambda: bus.alive("ant/alive/robot_io/robot-io-ros2", timeout_s=0.5), 90, "robot-io up")
        client = RobotClient(TypedBus(bus), "r2", timeout_s=60)
        errors: list[BaseException] = []

        def turn():
            try:
                client.turn(math.radians(700))  # within the schema's two turns, long enough to interrupt
            except BaseException as exc:  # the reply is an error or never comes: either is fine here
                errors.append(exc)

        th = threading.Thread(target=turn, daemon=True)
        th.start()
        wait_until(lambda: len([t for t in log.twists if t[1] != 0]) > 5, 30, "turning")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
        wait_until(lambda: log.twists[-1] == (0.0, 0.0), 10, "a zero twist last")
        # The stand-in's base stopped turning (it integrates the last command).
        h0 = s.robot.true_pose.heading_rad
        t0 = s.robot.t_s
        wait_until(lambda: s.robot.t_s > t0 + 1.0, 20, "a simulated second")
        assert abs(math.remainder(s.robot.true_pose.heading_rad - h0, 2 * math.pi)) < 1e-6
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        bus.close()
        log.close()
        s.close()
