"""A move that a jamb stops early is tried again a few centimetres aside (sidestep.py).

generated:2013:floors=2's noisy robot lost its stairs and its upper floor: the only way there is a
0.3 m lane beside a cabinet, the noisy map put the lane's middle 7 cm off the true one, and the move
down it stopped after 0.13 m on the cabinet's corner. The box world's robot stops at the first touch,
so these tests pass or fail on the geometry alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry import PinholeCamera
from shared.schemas import MoveStatus, Pose

from services.mapper.core.sidestep import SidestepConfig, move_sidestepping
from services.mapper.tools.boxworld import Box, BoxWorld, BoxWorldRobot

H = 2.6


def lane_world(gap_m: float = 0.3) -> BoxWorld:
    """A cabinet (x < 1.0) and a wall (x > 1.0 + gap) with a lane between them from y 1 to 3 m; open
    floor south and north of them."""
    boxes = [Box((0.0, 1.0, 0.0), (1.0, 3.0, 1.0)), Box((1.0 + gap_m, 1.0, 0.0), (2.5, 3.0, H))]
    return BoxWorld(boxes=boxes, floors=[Box((0.0, 0.0, -0.1), (2.5, 4.0, 0.0))], start=(1.15, 0.7, 0.0))


def robot_at(world: BoxWorld, x: float, y: float) -> BoxWorldRobot:
    robot = BoxWorldRobot(world, PinholeCamera(16, 16, 90.0), body_radius_m=0.1)
    robot.reset(Pose(position_m=[x, y, 0.0], heading_rad=0.0))
    return robot


@pytest.mark.parametrize("off_m", [-0.07, 0.07])
def test_a_move_down_a_lane_aimed_off_its_middle_gets_through(off_m):
    """The lane leaves 5 cm on either side of the 0.1 m body: aimed 7 cm off its middle, the move
    grazes a side. Tried again aside, it ends where it was meant to, either side."""
    world = lane_world()
    x = 1.15 + off_m
    plain = robot_at(world, x, 0.85)
    assert plain.move_to(0.0, 2.5).status == MoveStatus.BLOCKED  # the geometry the test relies on
    robot = robot_at(world, x, 0.85)
    res = move_sidestepping(robot, 0.0, 2.5, SidestepConfig())
    assert res.status == MoveStatus.REACHED
    assert np.allclose(robot.pose.xyz[:2], [x, 3.35], atol=0.02)  # the move's own end, past the lane
    assert res.travelled_m == pytest.approx(2.5)


def test_a_wall_is_not_walked_through_and_the_robot_ends_where_it_started():
    world = lane_world()
    robot = robot_at(world, 0.5, 0.8)  # in front of the cabinet: no lane within 10 cm
    first = robot_at(world, 0.5, 0.8).move_to(0.0, 1.0)
    res = move_sidestepping(robot, 0.0, 1.0, SidestepConfig())
    assert res.status == MoveStatus.BLOCKED
    assert res.travelled_m == pytest.approx(first.travelled_m)  # as if it had not been tried again
    assert np.allclose(robot.pose.xyz[:2], [0.5, 0.8], atol=0.02)


@pytest.mark.parametrize("bad", [{"offsets_m": (float("nan"),)}, {"offsets_m": (0.0,)}, {"offsets_m": (0.6,)},
                                 {"offsets_m": (-0.05,)}, {"early_m": float("inf")}, {"min_move_m": -1.0}])
def test_a_config_out_of_range_is_refused(bad):
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        SidestepConfig(**bad)


def test_a_move_blocked_late_or_a_config_without_offsets_is_left_to_the_caller():
    world = lane_world()
    far = robot_at(world, 0.5, 0.2)  # 0.7 m to the cabinet: blocked past early_m
    res = move_sidestepping(far, 0.0, 1.5, SidestepConfig())
    assert res.status == MoveStatus.BLOCKED and res.travelled_m > 0.3
    assert far.pose.xyz[1] > 0.5  # it stays where it stopped: the caller takes a panorama there
    off = robot_at(world, 1.22, 0.85)
    assert move_sidestepping(off, 0.0, 1.5, SidestepConfig(offsets_m=())).status == MoveStatus.BLOCKED


def _lane_graph(narrow: bool):
    """The exploration's two nodes either side of the lane, 7 cm off its middle, joined by a straight edge
    (marked narrow where the exploration laid it on the way to a frontier only the narrow body reaches)."""
    from types import SimpleNamespace

    from services.mapper.core.navgraph import GridGraph

    g = GridGraph()
    south, north = (g.add_visited(np.array([1.08, y, 0.0]), order=k) for k, y in enumerate((0.85, 3.35)))
    g.connect(south, north, narrow=narrow)
    return SimpleNamespace(result=SimpleNamespace(graph=g))


@pytest.mark.parametrize("narrow", [True, False])
def test_a_tour_transit_sidesteps_only_along_an_edge_laid_through_a_narrow_passage(narrow):
    """A tour's transit walks a narrow edge the way the exploration did; without the sidestep it is stopped at
    the lane's mouth and stays on the south side. An edge not marked narrow is walked as before, sidestep or
    not: a plain wall is never tried aside."""
    from services.mapper.core.execute import _transit

    world = lane_world()
    for sidestep in (None, SidestepConfig()):
        robot = robot_at(world, 1.08, 0.85)
        _transit(robot, _lane_graph(narrow), np.array([1.08, 3.35, 0.0]), sidestep=sidestep)
        assert (robot.pose.xyz[1] > 3.0) == (narrow and sidestep is not None), sidestep


def test_a_narrow_mark_is_kept_when_the_edge_is_walked_again_plainly():
    """A narrow edge walked again by a plain move (a transit that did not need the sidestep) stays narrow."""
    g = _lane_graph(True).result.graph
    a, b = list(g.g)
    g.connect(a, b, 1.0)
    assert g.narrow(a, b) and g.narrow(b, a)
    assert not _lane_graph(False).result.graph.narrow(a, b)


def _explore_bed_room(gap_m: float, monkeypatch):
    """The exploration of test_narrow_passages' bed room, every call of the sidestep recorded."""
    import services.mapper.core.explorer as explorer_mod
    from services.mapper.core import DiscoveryConfig, Explorer, PREDICTORS
    from tests.unit.mapper.test_narrow_passages import bed_room

    calls = []

    def spy(robot, dx_m, dy_m, cfg):
        calls.append((dx_m, dy_m))
        return move_sidestepping(robot, dx_m, dy_m, cfg)

    monkeypatch.setattr(explorer_mod, "move_sidestepping", spy)
    cfg = DiscoveryConfig()
    robot = BoxWorldRobot(bed_room(gap_m), PinholeCamera(48, 48, 90.0), body_radius_m=0.1)
    r = Explorer(PREDICTORS.create(cfg.predictor, cfg.predictor_config), cfg.exploration).explore(robot)
    return r, calls


def test_the_explorer_sidesteps_only_on_its_way_through_a_passage_the_map_holds_as_narrow(monkeypatch):
    """Through the bed room's 0.35 m gap (only the narrow body passes it on the map) the moves may sidestep,
    and the edges across the gap are marked narrow for the tours; with a 0.6 m gap (the map's own body
    passes) the same exploration blocks moves on furniture and walls, yet never tries one aside."""
    from services.mapper.core import NodeStatus

    r, calls = _explore_bed_room(0.35, monkeypatch)
    assert r.narrow_frontiers >= 1 and calls
    g = r.graph

    def crosses_the_bed(a: str, b: str) -> bool:  # the bed and the nightstand stand from y 3.0 to 3.6 m
        south, north = sorted((g.pos(a)[1], g.pos(b)[1]))
        return south < 3.0 and north > 3.6

    across = [(a, b) for a, b in g.walked().edges if crosses_the_bed(a, b)]
    assert across and all(g.narrow(a, b) for a, b in across), across
    north = g.positions(g.nodes_with(NodeStatus.VISITED))[:, 1] > 3.6
    assert north.sum() >= 3

    wide, calls = _explore_bed_room(0.6, monkeypatch)
    assert wide.narrow_frontiers == 0 and wide.blocked_moves >= 1
    assert calls == []
    assert not any(wide.graph.narrow(a, b) for a, b in wide.graph.walked().edges)
