"""The exploration re-placed by the pose graph (replace.py): under drift its graph nodes, scans and
trajectory end where the panoramas are after the solve, nearer the truth than before it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.geometry import PinholeCamera
from shared.schemas import MoveResult, Panorama

import services.mapper.core.discovery as discovery
from services.mapper.core import DiscoveryConfig, ExplorationConfig, NodeStatus, discover
from services.mapper.core.localise import LocaliserConfig
from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world
from tests.unit.mapper.test_localise import DriftingRobot


class PathDriftingRobot(DriftingRobot):
    """Odometry off by (20, -13) mm and 0.3 deg times the square root of the metres driven, as the
    simulator's drift grows; keeps the true pose of every panorama by its timestamp."""

    def __init__(self, robot: BoxWorldRobot):
        super().__init__(robot)
        self.driven_m = 0.0
        self.pano_truth: dict[float, tuple[float, float, float]] = {}

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult:
        before = self.robot.pose.position_m
        res = self.robot.move_to(dx_m, dy_m)
        self.driven_m += math.hypot(res.pose.position_m[0] - before[0], res.pose.position_m[1] - before[1])
        k = math.sqrt(self.driven_m)
        self.offset = (0.02 * k, -0.013 * k, math.radians(0.3) * k)
        return res.model_copy(update={"pose": self._odom(res.pose)})

    def observe(self) -> Panorama:
        pano = super().observe()
        p = self.robot.pose
        self.pano_truth[pano.timestamp_s] = (p.position_m[0], p.position_m[1], p.heading_rad)
        return pano


@pytest.fixture(scope="module")
def drifted():
    """One drifting exploration; the graph's visited positions as they were before the re-placement."""
    robot = PathDriftingRobot(BoxWorldRobot(rooms_world(), PinholeCamera(48, 48, 90.0)))
    cfg = DiscoveryConfig(exploration=ExplorationConfig(max_steps=14),
                          localisation=LocaliserConfig(replace_exploration=True))
    seen = {}
    real = discovery.replace_exploration

    def spy(result, localiser, before):
        g = result.graph
        seen["before"] = {n: g.pos(n).copy() for n in g.g}
        seen["trajectory"] = result.trajectory_m.copy()
        return real(result, localiser, before)

    mp = pytest.MonkeyPatch()
    mp.setattr(discovery, "replace_exploration", spy)
    try:
        d = discover(robot, cfg)
    finally:
        mp.undo()
    return robot, d, seen


def test_the_graph_follows_the_corrected_panoramas(drifted):
    robot, d, seen = drifted
    loc = d.scene.localiser
    assert loc.graph.report.applied  # the solve moved the panoramas: else there is nothing to follow
    g = d.result.graph
    placed = {s.timestamp_s: s.correction.pose(s.odom) for s in loc.steps}
    errors_before, errors_after = [], []
    for n in g.nodes_with(NodeStatus.VISITED):
        scan = d.result.scans[g.g.nodes[n]["order"] - 1]
        assert scan.node == n
        p = placed[scan.timestamp_s]
        # The node, its scan and its trajectory entry are where the pose graph put its panorama.
        assert np.allclose(g.pos(n)[:2], p.position_m[:2], atol=1e-9), (n, g.pos(n), p)
        assert np.allclose(scan.position_m[:2], p.position_m[:2], atol=1e-9)
        assert scan.heading_rad == pytest.approx(p.heading_rad, abs=1e-9)
        assert np.allclose(d.result.trajectory_m[scan.trajectory_index, :2], p.position_m[:2], atol=1e-9)
        true = robot.pano_truth[scan.timestamp_s]
        errors_before.append(math.hypot(*(seen["before"][n][:2] - true[:2])))
        errors_after.append(math.hypot(*(g.pos(n)[:2] - true[:2])))
    before, after = np.median(errors_before), np.median(errors_after)
    assert before > 0.01 and after < 0.8 * before, (before, after)
    # The record of it goes with the map's pose graph summary.
    s = loc.graph_summary()
    assert s.nodes_moved > 0 and 0.0 < s.median_node_shift_m <= s.max_node_shift_m < 0.2, s
    assert s.weak_edges == loc.graph.report.weak_edges <= s.scan_edges, s
    # Node ids stay, and the spatial index answers at the new positions.
    assert set(seen["before"]) == set(g.g)
    for n in g.nodes_with(NodeStatus.VISITED):
        assert n in g.near(g.pos(n), 1e-3, 0.1)


def test_observed_nodes_keep_their_place_seen_from_their_parent(drifted):
    """A candidate was measured in its parent panorama's views: it turns and shifts with that
    panorama, its distance to the parent unchanged."""
    _, d, seen = drifted
    g = d.result.graph
    observed = [n for n in g.g if g.status(n) != NodeStatus.VISITED and g.g.nodes[n].get("parent") in g.g]
    assert observed
    moved = 0
    for n in observed:
        par = g.g.nodes[n]["parent"]
        r_before = np.linalg.norm(seen["before"][n][:2] - seen["before"][par][:2])
        assert np.linalg.norm(g.pos(n)[:2] - g.pos(par)[:2]) == pytest.approx(r_before, abs=1e-9)
        assert g.pos(n)[2] == seen["before"][n][2]
        moved += bool(np.any(g.pos(n) != seen["before"][n]))
    assert moved > 0
    # The trajectory's moves: each between its panoramas' new places, none left where it was.
    assert d.result.trajectory_m.shape == seen["trajectory"].shape
    assert np.any(d.result.trajectory_m != seen["trajectory"])


def test_off_by_default_the_graph_stays_where_dead_reckoning_put_it(monkeypatch):
    """Off by default (LocaliserConfig.replace_exploration: the maps built from the tours it plans
    navigated worse): the exploration-end solve still runs, the graph is not moved."""
    calls = []
    monkeypatch.setattr(discovery, "replace_exploration", lambda *a: calls.append(a))
    robot = PathDriftingRobot(BoxWorldRobot(rooms_world(), PinholeCamera(48, 48, 90.0)))
    d = discover(robot, DiscoveryConfig(exploration=ExplorationConfig(max_steps=4)))
    assert calls == [] and d.scene.localiser is not None
    assert d.scene.localiser.graph_summary().nodes_moved == 0
