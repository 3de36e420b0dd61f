"""An exploration graph in two parts that touch only on a flight of stairs is rejoined where they touch.

A drifting robot slid off a flight and climbed on from where it landed: the upper floor became a part of
the graph with no traversed edge to the rest, and the only place where the two parts meet is the stairs,
a floor below the robot. generated:1011:floors=2 (noisy) gave up 21 ground-floor frontiers so."""

from __future__ import annotations

import networkx as nx
import numpy as np

from shared.schemas import MoveResult, MoveStatus, Pose

from services.mapper.core import ExplorationConfig, Explorer
from services.mapper.core.explorer import _Run

STOREY_M = 2.8


def _height(x_m: float) -> float:
    """A straight flight along x: ground floor before x = 2 m, upper floor after x = 4 m."""
    return float(np.clip((x_m - 2.0) / 2.0, 0.0, 1.0) * STOREY_M)


class StairRobot:
    """Goes anywhere on the flight's floors except across the segments in ``walls`` (either way)."""

    def __init__(self, start_xy, walls=()):
        self.p = np.array([*start_xy, _height(start_xy[0])], float)
        self.walls = [sorted([tuple(a), tuple(b)]) for a, b in walls]
        self.moves: list[tuple[tuple, tuple]] = []
        self.stuck = False

    @property
    def pose(self) -> Pose:
        return Pose(position_m=tuple(self.p), heading_rad=0.0)

    slide_to = None  # where a blocked move leaves the robot, stuck there (None: where it was, free)

    def move_to(self, dx_m, dy_m):
        a, b = tuple(np.round(self.p[:2], 6)), tuple(np.round(self.p[:2] + [dx_m, dy_m], 6))
        self.moves.append((a, b))
        if self.stuck:
            return MoveResult(status=MoveStatus.BLOCKED, pose=self.pose, travelled_m=0.0, steps=0)
        if sorted([a, b]) in self.walls:
            if self.slide_to is not None:
                self.p, self.stuck = np.array([*self.slide_to, _height(self.slide_to[0])]), True
            return MoveResult(status=MoveStatus.BLOCKED, pose=self.pose, travelled_m=0.0, steps=0)
        self.p = np.array([*b, _height(b[0])])
        return MoveResult(status=MoveStatus.REACHED, pose=self.pose, travelled_m=float(np.hypot(dx_m, dy_m)), steps=1)


def _two_parts(robot, second_crossing=False):
    """Upper part: two upper-floor nodes and two stair nodes; lower part: two ground-floor nodes and a
    stair node 0.2 m beside the upper part's lowest one. The robot stands on the upper floor."""
    run = _Run(Explorer(config=ExplorationConfig()), robot)
    g = run.graph

    def node(x, y, k):
        return g.add_visited(np.array([x, y, _height(x)]), order=k)

    upper = [node(6.0, 0.0, 0), node(5.0, 0.0, 1), node(3.5, 0.0, 2), node(3.0, 0.0, 3)]
    lower = [node(0.0, 0.2, 4), node(1.5, 0.2, 5), node(3.0, 0.2, 6)]
    if second_crossing:  # a stair node beside the upper part's second-lowest one, too
        lower.append(node(3.5, 0.2, 7))
    for part in (upper, lower):
        for a, b in zip(part, part[1:]):
            g.connect(a, b)
    run.here, run.pose = upper[0], robot.pose
    return run, upper, lower


def test_parts_that_touch_on_the_stairs_are_rejoined_there():
    run, upper, lower = _two_parts(StairRobot((6.0, 0.0)))
    assert not nx.has_path(run.graph.walked(), upper[0], lower[0])
    assert run._walk_to(lower[0])
    assert run.here == lower[0] and np.allclose(run.robot.p, [0.0, 0.2, 0.0])
    assert run.graph.walked().has_edge(upper[3], lower[2])  # the crossing, now a traversed edge


def test_a_crossing_the_robot_cannot_make_rejoins_nothing():
    wall = ((3.0, 0.0), (3.0, 0.2))  # a banister between the two stair nodes
    run, upper, lower = _two_parts(StairRobot((6.0, 0.0), walls=[wall]))
    assert not run._walk_to(lower[0])
    assert not nx.has_path(run.graph.walked(), upper[0], lower[0])
    assert run.blocked >= 1 and np.allclose(run.robot.p[:2], [3.0, 0.0])  # back on its own side


def test_a_crossing_that_leaves_the_robot_stranded_ends_the_bridge_without_an_error():
    """The blocked crossing slid the robot down the flight, where it is stuck: it does not get back, its
    panorama there is a new node of no part, and the bridge must not plan its next crossing from it."""
    robot = StairRobot((6.0, 0.0), walls=[((3.0, 0.0), (3.0, 0.2))])
    robot.slide_to = (2.6, 0.0)
    run, upper, lower = _two_parts(robot, second_crossing=True)
    run.arrive = lambda pano, previous, travelled_m: _stranded_node(run)
    run.robot.observe = lambda: None
    assert not run._walk_to(lower[0])
    assert run.here not in upper + lower and np.allclose(run.robot.p[:2], [2.6, 0.0])


def _stranded_node(run):
    run.here = run.graph.add_visited(run.robot.p.copy(), order=99)
    return run.here
