"""Fixtures of the mapper tests: the small box-room world and robot."""

from __future__ import annotations

import pytest

from shared.geometry import PinholeCamera

from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world


@pytest.fixture(scope="module")
def world():
    return rooms_world()


@pytest.fixture()
def robot(world):
    return BoxWorldRobot(world, PinholeCamera(48, 48, 90.0))
