"""The compiled ``NavGrid.walk`` gives exactly the array version's points, on one floor and on stairs."""

from __future__ import annotations

import numpy as np
import pytest

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
