"""Tour execution's transit over the exploration's traversed edges, when an edge cannot be walked back."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from shared.schemas import MoveResult, MoveStatus, Pose

from services.mapper.core.execute import _transit
from services.mapper.core.navgraph import GridGraph


class OneWayRobot:
    """Moves anywhere but along the segments in ``walls`` (either way): there it stops at once."""

    def __init__(self, start, walls):
        self.p = np.array(start, float)
        self.walls = [(np.array(a, float), np.array(b, float)) for a, b in walls]
        self.moves: list[tuple[np.ndarray, np.ndarray, bool]] = []

    @property
    def pose(self) -> Pose:
        return Pose(position_m=tuple(self.p), heading_rad=0.0)

    def move_to(self, dx_m, dy_m):
        goal = self.p + [dx_m, dy_m, 0.0]
        blocked = any(np.allclose(sorted([tuple(self.p[:2]), tuple(goal[:2])]), sorted([tuple(a), tuple(b)]))
                      for a, b in self.walls)
        self.moves.append((self.p.copy(), goal, blocked))
        if blocked:
            return MoveResult(status=MoveStatus.BLOCKED, pose=self.pose, travelled_m=0.0, steps=0)
        self.p = goal
        return MoveResult(status=MoveStatus.REACHED, pose=self.pose, travelled_m=float(np.hypot(dx_m, dy_m)), steps=1)


def _graph(points, edges):
    g = GridGraph()
    ids = [g.add_visited(np.array([x, y, 0.0]), order=k) for k, (x, y) in enumerate(points)]
    for a, b in edges:
        g.connect(ids[a], ids[b])
    return g, ids


def test_a_blocked_edge_is_planned_around():
    # A square a-b-c-d; the short way a -> b -> c has b -> c blocked; a -> d -> c is free.
    g, _ = _graph([(0, 0), (1, 0), (1, 1), (0, 1.2)], [(0, 1), (1, 2), (0, 3), (3, 2)])
    robot = OneWayRobot((0, 0, 0), walls=[((1, 0), (1, 1))])
    _transit(robot, SimpleNamespace(result=SimpleNamespace(graph=g)), np.array([1.0, 1.0, 0.0]))
    assert np.allclose(robot.p[:2], [1, 1])
    assert sum(blocked for *_, blocked in robot.moves) == 1


def test_a_node_whose_only_edge_is_blocked_rejoins_the_graph_directly():
    """The exploration's last node was reached out of a nook by a slide: its one edge cannot be
    walked back, so transit leaves it by a direct move to the nearest node of the rest."""
    g, _ = _graph([(0, 0), (1, 0), (2, 0), (2, 1.5)], [(0, 1), (1, 2), (2, 3)])
    robot = OneWayRobot((2, 1.5, 0), walls=[((2, 1.5), (2, 0))])
    _transit(robot, SimpleNamespace(result=SimpleNamespace(graph=g)), np.array([0.0, 0.0, 0.0]))
    assert np.allclose(robot.p[:2], [0, 0])
