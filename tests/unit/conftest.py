"""Simulators of the generated houses, built once per test session (the world library's, robot-io's and
the services' unit tests share them)."""

from __future__ import annotations

import pytest

from services.robot_io.core.robot import SimConfig, SimRobot


@pytest.fixture(scope="session")
def house_robot() -> SimRobot:
    return SimRobot(SimConfig(scene="generated:0", camera={"width_px": 64, "height_px": 64}))


@pytest.fixture(scope="session")
def two_floor_robot() -> SimRobot:
    return SimRobot(SimConfig(scene="generated:1:floors=2:area=160", camera={"width_px": 64, "height_px": 64}))
