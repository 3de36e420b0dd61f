"""The compiled ``NavGrid.walk`` gives exactly the array version's points, on one floor and on stairs; the
compiled obstacle pass builds exactly the array version's grid."""

from __future__ import annotations

import numpy as np
import pytest

from libs.world.navgrid import NavGrid, _compiled
from libs.world.scene import load_scene
from shared.jit import AVAILABLE

pytestmark = pytest.mark.skipif(not AVAILABLE, reason="numba is not installed: only the array version runs")


def _both(nav, a, b):
    nav.use_kernel = True
    try:
        fast = nav.walk(a, b)
        nav.use_kernel = False
        slow = nav.walk(a, b)
    finally:
        nav.use_kernel = True
    return fast, slow


def _walks(nav, rng, n):
    """Starts on walkable nodes (jittered inside their cell, some lifted by a few cm), goals up to 2 m
    away in any direction (through walls, off the grid, up and down stairs), plus starts off the grid."""
    starts = nav.nodes_m[rng.integers(0, len(nav.nodes_m), n)].copy()
    starts[:, :2] += rng.uniform(-0.5, 0.5, (n, 2)) * nav.cell_m
    starts[:, 2] += rng.choice([0.0, 0.05, 0.3], n)  # 0.3 m is beyond locate's tolerance: not on the grid
    ang = rng.uniform(-np.pi, np.pi, n)
    dist = rng.choice([0.0, 0.01, 0.25, 2.0], n) * rng.uniform(0.5, 1.0, n)
    goals = starts + np.column_stack([dist * np.cos(ang), dist * np.sin(ang), np.zeros(n)])
    return starts, goals


@pytest.mark.parametrize("robot", ["house_robot", "two_floor_robot"])
def test_compiled_walk_matches_the_array_version_bit_for_bit(robot, request):
    nav = request.getfixturevalue(robot).nav
    rng = np.random.default_rng(7)
    starts, goals = _walks(nav, rng, 1500)
    # Off the grid entirely, and a goal far outside it.
    lo = nav.origin
    starts = np.vstack([starts, [lo[0] - 1.0, lo[1] - 1.0, 0.0]])
    goals = np.vstack([goals, [lo[0] - 2.0, lo[1], 0.0]])
    starts = np.vstack([starts, starts[0]])
    goals = np.vstack([goals, [lo[0] - 5.0, lo[1] - 5.0, starts[0, 2]]])
    outcomes = {True: 0, False: 0}
    climbed = 0
    for a, b in zip(starts, goals):
        (p_fast, ok_fast), (p_slow, ok_slow) = _both(nav, a, b)
        assert ok_fast == ok_slow
        assert p_fast.tobytes() == p_slow.tobytes(), (a, b, p_fast, p_slow)
        outcomes[ok_fast] += 1
        climbed += abs(p_fast[2] - a[2]) > 0.1  # up or down a flight
    # Both outcomes are exercised (else the comparison proves little).
    assert outcomes[True] > 100 and outcomes[False] > 100
    if robot == "two_floor_robot":
        assert climbed > 0


class _Counting(NavGrid):
    """A grid that counts the nodes its obstacle pass blocked."""

    def _prune_obstacles(self, *args):
        before = int(np.isfinite(self._zgrid).sum())
        super()._prune_obstacles(*args)
        self.blocked = before - int(np.isfinite(self._zgrid).sum())


class _ArrayCounting(_Counting):
    use_kernel = False  # every pass as arrays, from the constructor on


def test_compiled_obstacle_pass_builds_the_array_versions_grid_bit_for_bit():
    # Three floors joined by two flights, furniture in every room: walls, stair sides and furniture
    # block nodes on each floor.
    scene = load_scene("generated:1:area=100:floors=3")
    fast, slow = _Counting(scene), _ArrayCounting(scene)
    assert fast._zgrid.tobytes() == slow._zgrid.tobytes()
    assert fast.nodes_m.tobytes() == slow.nodes_m.tobytes()
    assert (fast.graph != slow.graph).nnz == 0
    assert fast.blocked == slow.blocked > 1000, (fast.blocked, slow.blocked)  # else it proves little


def test_the_compiled_obstacle_pass_leaves_to_the_arrays_what_it_cannot_decide():
    # A wall's points (x 0..1, z 0..2), one node in the next column at floor height: blocked. With no
    # point on the grid, or a node so high above the points that its height band could reach a
    # neighbouring column's keys in the array version's one sorted array, the kernel declines (-1).
    kernel = _compiled("obstacles")
    tris = np.array([[[0.0, 0.5, 0.0], [1.0, 0.5, 0.0], [1.0, 0.5, 2.0]]])
    idx = np.zeros(2000, np.int64)
    rng = np.random.default_rng(0)
    r1, r2 = np.sqrt(rng.random(2000)), rng.random(2000)
    offsets = np.array([[0, 0], [0, 1], [0, -1]])

    def run(z_node, origin=(0.0, 0.0)):
        blocked = np.zeros(1, bool)
        status = kernel(tris, idx, r1, r2, np.array(origin), 0.5, 4, 4, np.array([1]), np.array([0]),
                        np.array([z_node]), offsets, 0.2, 1.5, blocked)
        return status, bool(blocked[0])

    assert run(0.0) == (1, True)
    assert run(5.0) == (1, False)  # above the wall: nothing in its band
    assert run(50.0)[0] == -1
    assert run(0.0, origin=(100.0, 100.0))[0] == -1  # every point off the grid
