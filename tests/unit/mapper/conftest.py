"""Fixtures of the mapper tests: the small box-room world and robot."""

from __future__ import annotations

import pytest

from shared.geometry import PinholeCamera

from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world


@pytest.fixture(scope="session")
def rooms_discovery():
    """``(world, robot, discovery)``: the box-room world explored by ``discover`` at 48 px.
    test_discovery's tests and test_tours' walked tours read the same exploration (1.5-5 s of CPU
    each time it runs); tests/conftest.py gives the two files one xdist group, so it runs once."""
    from services.mapper.core import discover

    world = rooms_world()
    robot = BoxWorldRobot(world, PinholeCamera(48, 48, 90.0))
    return world, robot, discover(robot)


@pytest.fixture(scope="module")
def world():
    return rooms_world()


@pytest.fixture()
def robot(world):
    return BoxWorldRobot(world, PinholeCamera(48, 48, 90.0))
