"""Stairs are found and climbed on every floor of generated buildings (the real simulator, 64 px views).

The 500 m2 two-floor house (seed 21) is the regression of issue 21: the flight was climbed to its
last treads, where too few steps remain in view to tell a staircase from furniture, and the robot
turned back, reporting a "finished" exploration of one floor out of two.

The 100 m2 three-floor house (seed 1) is the next one: the second flight's foot was visited, but the
way up was dropped as "already seen" because a bedroom node on the other side of the shaft's wall
stood within the visit radius; the third floor was never reached (64.6 % coverage, "finished").
A visited node now covers only what its own scan saw.

The 200 m2 three-floor house (seed 2) is the third: the only way to the first flight runs through
a dining room, past the table, whose lower half the robot saw between the chairs. The free-space
map's frontier there was given a target in the kitchen next door (the nearest free cell in a
straight line, through the wall), which the explorer rightly dropped as seen; no other cell of the
frontier was tried, and the exploration "finished" on the ground floor (27 % coverage, estimate 93 %).

The 200 m2 two-floor house (seed 4) is the fourth: a move back to a stair node half way up slid
off the flight's side, and the robot stood on the ground floor 0.7 m away while the graph held it
on the stairs; every frontier left was given up as out of reach (51 % coverage, one floor). A robot
that does not get back to its node now takes a panorama where it stands.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shared.schemas import CameraIntrinsics

from services.mapper.core import DiscoveryConfig, ExplorationConfig, Explorer, NodeStatus, PREDICTORS
from services.mapper.core.discovery import WIDE_EXPLORATION
from libs.world.house import STOREY_H
from services.robot_io.core.robot import ROBOTS

CAM = CameraIntrinsics(width_px=64, height_px=64, hfov_deg=90.0)


_DONE: dict[str, tuple] = {}  # one exploration per scene for the whole module


def _explore(scene: str):
    if scene not in _DONE:
        robot = ROBOTS.create("sim", {"scene": scene, "camera": CAM})
        cfg = DiscoveryConfig()
        result = Explorer(PREDICTORS.create(cfg.predictor, cfg.predictor_config), cfg.exploration).explore(robot)
        _DONE[scene] = (robot, result)
    return _DONE[scene]


def _floor_coverage(robot, result, radius_m: float = 1.5) -> list[float]:
    """Per storey: the share of the simulator's reachable cells within ``radius_m`` of a visited node."""
    nav = robot.nav
    reach = nav.nodes_m[nav.component == nav.main_component][::4]
    g = result.graph
    nodes = g.positions(g.nodes_with(NodeStatus.VISITED))
    scale = np.array([1.0, 1.0, 4.0])
    dist, _ = cKDTree(nodes * scale).query(reach * scale)
    out = []
    for fl in range(robot.scene.floors):
        on = np.abs(reach[:, 2] - fl * STOREY_H) < 0.05
        out.append(float((dist[on] <= radius_m).mean()))
    return out


@pytest.mark.parametrize("scene", [
    "generated:21:area=500:floors=2",  # the regression
    "generated:7:area=150:floors=2",
    "generated:0:area=100:floors=2",
    "generated:1:area=100:floors=3",  # the second flight's foot behind a wall (see above)
    "generated:4:area=200:floors=2",  # slid off the flight on the way back (see above)
])
def test_every_floor_is_reached_and_explored(scene):
    robot, r = _explore(scene)
    cover = _floor_coverage(robot, r)
    assert min(cover) >= 0.9, f"coverage per floor {np.round(cover, 3)}"
    assert r.finished and r.stop_reason == "exhausted" and r.open_stairs == 0
    assert r.steps < r.step_budget


def test_an_unfinished_flight_keeps_the_exploration_unfinished():
    """Cut the climb short: the budget stops the robot on the stairs, and the result says so."""
    robot, full = _explore("generated:1:area=100:floors=3")
    cfg = DiscoveryConfig()
    # The step at which the robot first stood on the stairs, half way up the first flight.
    z = np.array([full.graph.pos(n)[2] for n in full.visit_order])
    first = int(np.argmax((z > 0.5) & (z < STOREY_H - 0.5)))
    assert first > 0
    robot.reset(full.start_pose)
    short = Explorer(PREDICTORS.create(cfg.predictor, cfg.predictor_config),
                     ExplorationConfig(max_steps=first + 1)).explore(robot)
    assert not short.finished and short.stop_reason == "steps"
    assert short.open_stairs >= 1


def test_the_way_through_the_dining_room_is_found():
    """generated:2:area=200:floors=3 (see above): the map's frontier in the dining room leads past
    the table to the flight. The exploration before the fix ended at step 62; the robot now stands
    on the first flight by step 68 (a budget of 80 keeps the test short)."""
    robot = ROBOTS.create("sim", {"scene": "generated:2:area=200:floors=3", "camera": CAM})
    cfg = DiscoveryConfig()
    r = Explorer(PREDICTORS.create(cfg.predictor, cfg.predictor_config),
                 cfg.exploration.model_copy(update={"max_steps": 80})).explore(robot)
    pos = np.array([r.graph.pos(n) for n in r.visit_order])
    dining = (pos[:, 0] > 5.9) & (pos[:, 1] < 2.8) & (np.abs(pos[:, 2]) < 0.2)  # past the table
    assert dining.any(), "the lower dining room was never entered"
    assert (pos[:, 2] > 0.5).any(), f"never on the stairs in {r.steps} steps ({r.stop_reason})"
    assert r.map_frontiers >= 1  # the predictor alone does not find the way
    assert not r.finished  # stopped by the budget, on the way up
