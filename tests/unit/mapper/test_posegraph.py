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
    # The wrong closure claims a well-pinned edge's information (not a pair's through the door,
    # pinned one way only: that one says nothing about a slide along it).
    good = max((e for e in g.edges.values() if e is not None),
               key=lambda e: np.linalg.eigvalsh(e.info)[0])
    c, s = math.cos(truth[0][2]), math.sin(truth[0][2])
    d = truth[last][:2] - truth[0][:2] + (0.4, 0.0)
    z = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], float(wrap_angle(truth[last][2] - truth[0][2]))])
    g.edges[(0, last)] = Edge(0, last, z, good.info.copy(), True, 0.9, 0.01)
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


def _corridor_walk() -> tuple[np.ndarray, list]:
    """(true poses, scans) of six panoramas along the localiser's featureless corridor."""
    from tests.unit.mapper.test_localise import corridor_world

    robot = BoxWorldRobot(corridor_world(), PinholeCamera(64, 64, 90.0))
    cfg = LocaliserConfig(band_from_median=True)
    truth, scans = [], []
    for k in range(6):
        x = -4.0 + 1.2 * k
        robot.reset(Pose(position_m=(x, 0.8, 0.0), heading_rad=float(wrap_angle(0.9 * k))))
        pano = robot.observe()
        truth.append(np.array([x, 0.8, pano.pose.heading_rad]))
        scans.append(panorama_scan(pano, cfg))
    return np.array(truth), scans


CORRIDOR_DRIFT = np.array([0.02, 0.05, math.radians(0.3)])
# Odometry as uncertain as this drift (the defaults allow 2x the noisy row's, 2.7 cm a step).
WIDE = PoseGraphConfig(odom_m_per_sqrt_m=0.1, odom_rad_per_sqrt_move=0.02)


def _across_only(g: PoseGraph, truth: np.ndarray) -> None:
    """The corridor's drift across it and in heading taken out, the one along it kept as odometry has it."""
    x = np.array([n.pose for n in g.nodes])
    odom = truth + np.arange(len(truth))[:, None] * CORRIDOR_DRIFT
    assert np.abs(x[:, 1] - truth[:, 1]).max() < 0.01, x[:, 1] - truth[:, 1]  # across: 25 cm of drift gone
    assert np.degrees(np.abs(wrap_angle(x[:, 2] - truth[:, 2]))).max() < 0.15
    assert np.abs(x[:, 0] - odom[:, 0]).max() < 0.01, x[:, 0] - odom[:, 0]  # along: odometry's


def test_a_pair_that_pins_one_direction_ties_it_and_leaves_the_other():
    """A corridor (the localiser's featureless one): each pair of panoramas along it pins the robot
    across it and in heading, not along it. Such pairs are edges across only (the rooms of a house
    seen through their doors were tied by odometry alone without them, and the two-floor house's
    upper floor drifted room by room): the drift across is taken out, the one along kept as odometry
    has it, never pulled to wherever the matcher slid."""
    truth, scans = _corridor_walk()
    off = _graph(truth, scans, CORRIDOR_DRIFT, WIDE)
    assert not off.solve().applied and not [e for e in off.edges.values() if e is not None]
    g = _graph(truth, scans, CORRIDOR_DRIFT, WIDE.model_copy(update={"weak_edges": True}))
    rep = g.solve()
    assert rep.applied and rep.scan_edges >= 5, rep
    _across_only(g, truth)


def test_the_final_solve_takes_the_pairs_pinned_one_way():
    """The solve before the recordings are re-placed (nothing is driven after it) takes the pairs
    pinned one way only as edges along that way, which the solves that drive the route leave out
    (PoseGraphConfig.final_weak_edges)."""
    truth, scans = _corridor_walk()
    g = _graph(truth, scans, CORRIDOR_DRIFT, WIDE)
    assert not g.solve().applied and not [e for e in g.edges.values() if e is not None]
    rep = g.solve(final=True)
    assert rep.applied and rep.scan_edges >= 5 and rep.weak_edges == rep.scan_edges, rep
    _across_only(g, truth)
    off = _graph(truth, scans, CORRIDOR_DRIFT, WIDE.model_copy(update={"final_weak_edges": False}))
    assert not off.solve(final=True).applied


def _wall_scan(pose: np.ndarray, walls: list[tuple[tuple[float, float], tuple[float, float]]]) -> np.ndarray:
    """A scan (robot frame x, y, standard error) of points every 2.5 cm along ``walls`` (world segments)."""
    pts = []
    for (x0, y0), (x1, y1) in walls:
        n = int(math.hypot(x1 - x0, y1 - y0) / 0.025) + 1
        pts.append(np.stack([np.linspace(x0, x1, n), np.linspace(y0, y1, n)], axis=1))
    p = np.concatenate(pts) - pose[:2]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], np.full(len(p), 0.005)], axis=1)


def _two_rooms() -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """(true poses (2, 3), scans, the second's dead-reckoning error): two panoramas on either side of a
    door sharing one corner of walls; a sees the corner and its own room's far walls, b the corner and a
    long wall of its room."""
    corner = [((0.0, 0.0), (2.0, 0.0)), ((0.0, 0.0), (0.0, 1.5))]
    a, b = np.array([1.0, 0.8, 0.3]), np.array([1.6, 2.6, -0.4])
    scans = [_wall_scan(a, corner + [((2.0, -1.0), (2.0, 1.0))]),
             _wall_scan(b, corner + [((-2.0, 3.6), (5.0, 3.6)), ((5.0, 1.0), (5.0, 3.6))])]
    return np.array([a, b]), scans, np.array([0.03, -0.02, math.radians(0.5)])


def test_two_rooms_seen_through_a_door_are_tied():
    """Two panoramas on either side of a door share one corner of walls: a quarter of one's scan lies
    on the other's. That is under the localiser's 0.3 (a panorama placed against its model needs more),
    but both directions are pinned and the two registrations agree, so the pair is an edge
    (PoseGraphConfig.min_fitness 0.2): without it the rooms were tied by odometry alone."""
    truth, scans, drift = _two_rooms()
    a, b = truth

    def edge(cfg: PoseGraphConfig):
        g = _graph(truth, scans, drift, cfg)
        g._register_pairs()
        return g.edges[(0, 1)]

    assert edge(PoseGraphConfig(min_fitness=None)) is None  # the localiser's 0.3
    e = edge(PoseGraphConfig())
    assert e is not None and 0.2 <= e.fitness < 0.3, e
    c, s = math.cos(a[2]), math.sin(a[2])
    d = b[:2] - a[:2]
    true_z = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], b[2] - a[2]])
    assert np.hypot(*(e.z[:2] - true_z[:2])) < 0.005 and abs(e.z[2] - true_z[2]) < math.radians(0.1), (e.z, true_z)


def test_the_final_solve_trusts_the_scans_as_far_as_they_go():
    """Two rooms whose only tie is one pair seen through the door, the second panorama dead-reckoned
    3.6 cm and 0.5 deg off: a route-driving solve holds the pair no surer than 1 cm and 0.3 deg, so
    odometry keeps millimetres of its error; the final solve holds it as sure as the registration
    (PoseGraphConfig.final_edge_sigma_*: on the two-floor house the edges were 10 times surer than
    1 cm) and recovers the offset to a millimetre and 0.02 deg. Exact poses stay exact under it."""
    truth, scans, drift = _two_rooms()
    g, f = _graph(truth, scans, drift), _graph(truth, scans, drift)
    assert g.solve().applied and f.solve(final=True).applied
    pos_g, head_g = _errors(g, truth)
    pos_f, head_f = _errors(f, truth)
    assert pos_g[1] > 0.002, pos_g
    assert pos_f[1] < 0.001 and head_f[1] < 0.02, (pos_f, head_f)
    exact = _graph(truth, scans, np.zeros(3))
    assert not exact.solve(final=True).applied
    for n, t in zip(exact.nodes, truth):
        assert np.array_equal(n.pose, t)
