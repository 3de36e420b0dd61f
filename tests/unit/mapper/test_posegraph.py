"""The panoramas' pose graph (posegraph.py): a loop's drift closed, exact poses left bit for bit,
a wrong loop closure rejected, and the recordings re-placed between the panoramas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.geometry import PinholeCamera, interpolate_offsets, wrap_angle
from shared.schemas import Pose

from services.mapper.core.localise import LocaliserConfig, panorama_scan
from services.mapper.core.posegraph import Edge, PoseGraph, PoseGraphConfig
from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world

# A walk round the big room, through the door into the north room and back: the last panoramas
# revisit the first ones' places (the loop closures).
LOOP = [(1.5, 1.5), (3.0, 1.0), (4.8, 1.0), (5.0, 2.8), (3.5, 3.2), (2.0, 3.0), (2.0, 5.2), (3.5, 6.0),
        (5.5, 6.5), (3.0, 7.0), (1.2, 6.2), (2.0, 4.6), (1.8, 2.8), (1.4, 1.7)]


@pytest.fixture(scope="module")
def walk():
    """(true poses, scans) of the loop's panoramas, each heading somewhere else."""
    robot = BoxWorldRobot(rooms_world(), PinholeCamera(64, 64, 90.0))
    cfg = LocaliserConfig(band_from_median=True)
    truth, scans = [], []
    for k, (x, y) in enumerate(LOOP):
        robot.reset(Pose(position_m=(x, y, 0.0), heading_rad=float(wrap_angle(0.7 * k))))
        pano = robot.observe()
        truth.append(np.array([x, y, pano.pose.heading_rad]))
        scans.append(panorama_scan(pano, cfg))
    return np.array(truth), scans


def _graph(truth: np.ndarray, scans, drift_per_step: np.ndarray, config: PoseGraphConfig | None = None) -> PoseGraph:
    """The walk's nodes with odometry off by ``drift_per_step`` more at every panorama, each placed
    where odometry put it (the worst a sequential localiser can do: nothing)."""
    g = PoseGraph(config or PoseGraphConfig(), LocaliserConfig())
    path = 0.0
    for k, (t, scan) in enumerate(zip(truth, scans)):
        if k:
            path += float(np.hypot(*(t[:2] - truth[k - 1][:2])))
        odom = t + k * drift_per_step
        g.add(float(k), odom, 0.0, scan, path, k, odom)
    return g


def _errors(g: PoseGraph, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.array([n.pose for n in g.nodes])
    return np.hypot(*(x[:, :2] - truth[:, :2]).T), np.degrees(np.abs(wrap_angle(x[:, 2] - truth[:, 2])))


def test_a_loop_closes_the_drift(walk):
    """Odometry drifts 1.5 cm, -1 cm and 0.4 deg more at every panorama (20 cm and 5 deg by the loop's
    end); the scan edges, the loop closures among them, put every panorama within 1.5 cm and 0.3 deg
    of the truth, the first still exactly at the start."""
    truth, scans = walk
    g = _graph(truth, scans, np.array([0.015, -0.01, math.radians(0.4)]))
    before = _errors(g, truth)
    assert before[0].max() > 0.15
    rep = g.solve()
    pos, head = _errors(g, truth)
    assert rep.applied and rep.loop_closures_accepted >= 3 and rep.loop_closures_rejected == 0, rep
    assert pos.max() < 0.015 and head.max() < 0.3, (pos, head)
    assert np.array_equal(g.nodes[0].pose, truth[0])


def test_exact_poses_stay_exact(walk):
    """A noise-free walk: the graph agrees with the exact placements within the gate, and they stay
    as they were, bit for bit."""
    truth, scans = walk
    g = _graph(truth, scans, np.zeros(3))
    rep = g.solve()
    assert not rep.applied and rep.scan_edges > 10, rep
    assert rep.max_move_m < 0.005, rep
    for n, t in zip(g.nodes, truth):
        assert np.array_equal(n.pose, t)


def test_a_wrong_loop_closure_is_rejected(walk):
    """A loop closure that puts the last panorama 40 cm from where every other edge has it (a
    symmetric room's wrong basin) is rejected, and the graph still closes the drift."""
    truth, scans = walk
    g = _graph(truth, scans, np.array([0.01, 0.01, math.radians(0.2)]))
    g._register_pairs()
    last = len(g.nodes) - 1
    good = next(e for e in g.edges.values() if e is not None)
    c, s = math.cos(truth[0][2]), math.sin(truth[0][2])
    d = truth[last][:2] - truth[0][:2] + (0.4, 0.0)
    z = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], float(wrap_angle(truth[last][2] - truth[0][2]))])
    g.edges[(0, last)] = Edge(0, last, z, good.sqrt_info.copy(), True, 0.9, 0.01)
    rep = g.solve()
    assert not g.edges[(0, last)].accepted and rep.loop_closures_rejected >= 1, rep
    pos, head = _errors(g, truth)
    assert pos.max() < 0.02 and head.max() < 0.4, (pos, head)


def test_offsets_are_interpolated_in_time():
    """Between two fixes a correction grows linearly in time; before the first and after the last it
    is theirs; a heading across +-180 deg goes the short way."""
    t = [10.0, 20.0]
    o = [(0.0, 0.1, math.radians(179.0)), (0.2, -0.1, math.radians(-179.0))]
    got = interpolate_offsets(t, o, [5.0, 10.0, 15.0, 20.0, 25.0])
    assert np.allclose(got[:, 0], [0.0, 0.0, 0.1, 0.2, 0.2])
    assert np.allclose(got[:, 1], [0.1, 0.1, 0.0, -0.1, -0.1])
    assert abs(abs(got[2, 2]) - math.pi) < 1e-9  # half way from 179 to -179 deg: 180, not 0
    assert np.allclose(interpolate_offsets([3.0], [(1.0, 2.0, 0.5)], [0.0, 9.0]), [(1.0, 2.0, 0.5)] * 2)
