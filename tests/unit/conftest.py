"""Simulators of the generated houses, built once per test session (the world library's, robot-io's and
the services' unit tests share them)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from services.robot_io.core.robot import SimRobot

# The simulator is imported in the fixtures, not here: ``make test-unit`` names tests/unit, so the xdist
# controller loads this file before it starts its workers, and the simulator's imports (open3d, numba,
# scipy: 1.8 s of CPU with warm bytecode, more in a fresh clone) held back both workers' start. The
# workers import it anyway, with the tests that use it.


@pytest.fixture(scope="session")
def house_robot() -> SimRobot:
    from services.robot_io.core.robot import SimConfig, SimRobot

    return SimRobot(SimConfig(scene="generated:0", camera={"width_px": 64, "height_px": 64}))


@pytest.fixture(scope="session")
def two_floor_robot() -> SimRobot:
    from services.robot_io.core.robot import SimConfig, SimRobot

    return SimRobot(SimConfig(scene="generated:1:floors=2:area=160", camera={"width_px": 64, "height_px": 64}))


@pytest.fixture(scope="session")
def house_viewpoints(house_robot):
    """generated:0's eye positions over its walkable floor, as ``sample_scene_cloud`` finds them by default
    (``walkable_viewpoints``: a navigation grid of the scene's own, ~0.6 s of CPU): the clouds sampled from
    the house (below, and tests/unit/scenegraph's denser one) build it once, not once each."""
    from evaluation.clouds import walkable_viewpoints

    return walkable_viewpoints(house_robot.scene)


@pytest.fixture(scope="session")
def house_map_cloud(house_robot, house_viewpoints):
    """generated:0's visible surfaces at 60 points per m2 (57.5k points): the map cloud that the planner's
    and the scene graph's mission tests render and read. Sampled once (1.6e6 visibility rays, ~0.8 s of
    CPU) instead of once per file; it depends on the scene alone, and no test changes it."""
    from evaluation.clouds import sample_scene_cloud

    return sample_scene_cloud(house_robot.scene, density_per_m2=60.0, max_points=100_000,
                              viewpoints_m=house_viewpoints)
