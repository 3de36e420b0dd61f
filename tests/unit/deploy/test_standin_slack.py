"""``deploy.launcher.StandIn``: a faster stand-in clock keeps the wall time of the tolerances counted in
robot time (STANDIN_WALL_SLACK_S), and the configs it writes are ones the backend and the stand-in take."""

from __future__ import annotations

import json

import pytest

from deploy.launcher import STANDIN_WALL_SLACK_S, StandIn
from services.robot_io.core.ros2.backend import Ros2Config
from services.robot_io.core.ros2.standin import StandInConfig


def _configs(scale: float) -> tuple[Ros2Config, StandInConfig]:
    s = StandIn(scene="generated:3:area=50", keys="rmw_zenoh", time_scale=scale)
    backend = Ros2Config.model_validate(json.loads(s.robot_env("tcp/127.0.0.1:7447")["ANT_ROBOT_CONFIG"]))
    argv = s.argv("tcp/127.0.0.1:7447")
    standin = StandInConfig.model_validate(json.loads(argv[argv.index("--config") + 1]))
    return backend, standin


@pytest.mark.parametrize("scale", [8.0, 12.0])
def test_a_fast_clock_keeps_each_tolerances_wall_time(scale):
    backend, standin = _configs(scale)
    got = {("backend", k): getattr(backend, k) for k in ("deadline_margin_s", "stall_s")}
    got[("standin", "progress_timeout_s")] = standin.progress_timeout_s
    assert got.keys() == STANDIN_WALL_SLACK_S.keys()
    for key, (wall_s, _) in STANDIN_WALL_SLACK_S.items():
        assert got[key] == pytest.approx(wall_s * scale), key
    # The base's watchdog stays in robot time: a late robot-io finds the base stopped.
    assert standin.cmd_timeout_s == StandInConfig.model_fields["cmd_timeout_s"].default
    assert standin.time_scale == scale and backend.max_data_age_s == pytest.approx(0.5 * scale)


def test_at_scale_four_the_defaults_stand():
    backend, standin = _configs(4.0)
    for (who, name) in STANDIN_WALL_SLACK_S:
        cfg, cls = (backend, Ros2Config) if who == "backend" else (standin, StandInConfig)
        assert getattr(cfg, name) == cls.model_fields[name].default, name


def test_a_clock_fast_enough_to_pass_a_bound_gets_the_bound():
    backend, standin = _configs(100.0)  # the stand-in's fastest clock
    assert backend.stall_s == 30.0 and standin.progress_timeout_s == 120.0 and backend.deadline_margin_s == 250.0
