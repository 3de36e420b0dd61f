"""VLN-CE metrics against published reference values and independent computations."""

from __future__ import annotations

import gzip
import json
import math

import networkx as nx
import numpy as np
import pytest

from shared.vln_metrics import (
    MetricsError,
    dedupe_consecutive,
    dtw_distance,
    episode_metrics,
    euclidean_geodesic,
    ndtw,
    spl,
    summarize,
    trajectory_length,
)

# --- R4R dtw.py doctests (google-research/google-research, r4r/dtw.py) ------------------------------


@pytest.fixture(scope="module")
def r4r_case():
    graph = nx.grid_graph([3, 4])
    dist = dict(nx.all_pairs_dijkstra_path_length(graph))
    prediction = [(0, 0), (1, 0), (2, 0), (3, 0)]
    reference = [(0, 0), (1, 0), (2, 1), (3, 2)]
    return (lambda a, b: dist[a][b]), prediction, reference


def test_r4r_doctest_dtw(r4r_case):
    d, pred, ref = r4r_case
    assert np.isclose(dtw_distance(pred, ref, distance=d), 3.0)


def test_r4r_doctest_ndtw(r4r_case):
    d, pred, ref = r4r_case
    assert np.isclose(ndtw(pred, ref, distance=d), 0.77880078307140488)


def test_r4r_doctest_sdtw(r4r_case):
    d, pred, ref = r4r_case
    # sdtw = success * ndtw, success judged on the final position's distance to the goal.
    full_success = d(pred[-1], ref[-1]) < 3.0
    assert np.isclose(full_success * ndtw(pred, ref, distance=d), 0.77880078307140488)
    short_success = d(pred[:2][-1], ref[-1]) < 3.0
    assert np.isclose(short_success * ndtw(pred[:2], ref, distance=d), 0.0)


# --- DTW against an independent (recursive, memoised) implementation --------------------------------


def _dtw_reference(p, r):
    from functools import lru_cache

    @lru_cache(maxsize=None)
    def acc(i, j):
        c = float(np.linalg.norm(p[i] - r[j]))
        if i == 0 and j == 0:
            return c
        best = math.inf
        if i > 0:
            best = min(best, acc(i - 1, j))
        if j > 0:
            best = min(best, acc(i, j - 1))
        if i > 0 and j > 0:
            best = min(best, acc(i - 1, j - 1))
        return c + best

    return acc(len(p) - 1, len(r) - 1)


@pytest.mark.parametrize("n,m", [(1, 1), (1, 7), (6, 1), (5, 9), (13, 4), (20, 20)])
def test_exact_dtw_matches_textbook_recursion(n, m):
    rng = np.random.default_rng(n * 100 + m)
    p = rng.normal(size=(n, 3)) * 3
    r = rng.normal(size=(m, 3)) * 3
    assert dtw_distance(p, r) == pytest.approx(_dtw_reference(p, r), rel=1e-12)


def test_dtw_identical_paths_is_zero_and_symmetric():
    rng = np.random.default_rng(0)
    p = np.cumsum(rng.normal(size=(30, 3)), axis=0)
    q = np.cumsum(rng.normal(size=(17, 3)), axis=0)
    assert dtw_distance(p, p) == 0.0
    assert ndtw(p, p) == 1.0
    assert dtw_distance(p, q) == pytest.approx(dtw_distance(q, p))


def test_fast_dtw_option():
    pytest.importorskip("fastdtw")
    p = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    assert dtw_distance(p, p, method="fast") == 0.0


# --- episode metrics --------------------------------------------------------------------------------


def test_success_spl_tl_on_a_straight_walk():
    traj = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 2, 0.0]])
    goal = np.array([4.0, 2.0, 0.0])
    m = episode_metrics(traj, goal, geodesic=euclidean_geodesic, stop_called=True, shortest_m=4.0)
    assert m.tl_m == pytest.approx(4.0)
    assert m.ne_m == pytest.approx(2.0)
    assert m.success and m.oracle_success
    assert m.spl == pytest.approx(4.0 / max(4.0, 4.0))
    assert m.steps == 3 and m.goal_reachable


def test_success_requires_stop_and_strict_radius():
    traj = np.array([[0, 0, 0], [1, 0, 0.0]])
    goal = np.array([4.0, 0.0, 0.0])  # final NE exactly 3.0: not a success (habitat uses '<')
    m = episode_metrics(traj, goal, geodesic=euclidean_geodesic, stop_called=True)
    assert m.ne_m == pytest.approx(3.0) and not m.success and not m.oracle_success
    m2 = episode_metrics(traj, [3.5, 0, 0], geodesic=euclidean_geodesic, stop_called=False)
    assert not m2.success and m2.oracle_success and m2.spl == 0.0 and m2.sdtw is None


def test_oracle_success_when_passing_by_the_goal():
    traj = np.array([[0, 0, 0], [5, 0, 0], [10, 0, 0.0]])
    m = episode_metrics(traj, [5, 1, 0], geodesic=euclidean_geodesic, stop_called=True)
    assert m.oracle_success and not m.success
    assert m.oracle_ne_m == pytest.approx(1.0)


def test_spl_penalises_detours():
    # Goal 6 m away, the agent walks 6 + 4 m: SPL = 6 / 10.
    traj = np.array([[0, 0, 0], [0, 2, 0], [6, 2, 0], [6, 0, 0.0]])
    m = episode_metrics(traj, [6, 0, 0], geodesic=euclidean_geodesic, stop_called=True, shortest_m=6.0)
    assert m.success and m.spl == pytest.approx(0.6)
    assert spl(True, 0.0, 0.0) == 1.0
    assert spl(False, 5.0, 5.0) == 0.0
    assert spl(True, math.inf, 3.0) == 0.0


def test_unreachable_goal_is_reported_not_nan():
    def geodesic(a, b):
        return None if b[2] > 1.0 else euclidean_geodesic(a, b)  # the goal floor is not connected

    traj = np.array([[0, 0, 0], [1, 0, 0.0]])
    m = episode_metrics(traj, [0, 0, 3.0], geodesic=geodesic, stop_called=True, reference_path_m=traj)
    assert m.ne_m is None and m.oracle_ne_m is None and m.shortest_m is None
    assert not m.goal_reachable and not m.success and m.spl == 0.0
    d = json.loads(json.dumps(m.to_dict()))  # JSON-safe: no NaN/inf anywhere
    assert all(not (isinstance(v, float) and not math.isfinite(v)) for v in d.values())
    s = summarize([m, episode_metrics(traj, [1, 1, 0], geodesic=geodesic, stop_called=True)])
    assert s.unreachable == 1 and s.ne_m == pytest.approx(1.0) and s.sr == pytest.approx(0.5)


def test_nan_geodesic_is_an_error():
    with pytest.raises(MetricsError):
        episode_metrics([[0, 0, 0]], [1, 0, 0], geodesic=lambda a, b: float("nan"), stop_called=True)


def test_ndtw_dedupes_consecutive_positions_like_vlnce():
    ref = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    traj = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    assert len(dedupe_consecutive(traj)) == 3
    m = episode_metrics(traj, ref[-1], geodesic=euclidean_geodesic, stop_called=True, reference_path_m=ref)
    assert m.ndtw == 1.0 and m.sdtw == 1.0


def test_summary_percent_row():
    traj = np.array([[0, 0, 0], [2, 0, 0.0]])
    a = episode_metrics(traj, [2, 0, 0], geodesic=euclidean_geodesic, stop_called=True, reference_path_m=traj)
    b = episode_metrics(traj, [9, 0, 0], geodesic=euclidean_geodesic, stop_called=True, reference_path_m=traj)
    row = summarize([a, b]).as_percent_row()
    assert row["SR"] == 50.0 and row["OSR"] == 50.0 and row["SPL"] == 50.0
    assert row["NE"] == pytest.approx((0.0 + 7.0) / 2)
    with pytest.raises(MetricsError):
        summarize([])


# --- real R2R-CE ground truth -----------------------------------------------------------------------


def test_r2r_ce_ground_truth_paths_score_perfectly(shared_data):
    root = shared_data / "r2r_ce"
    ep_file = next(root.glob("*val_unseen.json.gz"))
    gt_file = next(root.glob("*_gt.json.gz"))
    with gzip.open(ep_file, "rt") as f:
        episodes = json.load(f)["episodes"][:25]
    with gzip.open(gt_file, "rt") as f:
        gt = json.load(f)
    for ep in episodes:
        locs = np.asarray(gt[str(ep["episode_id"])]["locations"], dtype=np.float64)
        goal = np.asarray(ep["goals"][0]["position"])
        # The dense shortest path, walked in 0.25 m / 15 deg actions: its length is close to the geodesic.
        assert trajectory_length(locs) == pytest.approx(ep["info"]["geodesic_distance"], rel=0.15)
        m = episode_metrics(
            locs, goal, geodesic=euclidean_geodesic, stop_called=True,
            shortest_m=ep["info"]["geodesic_distance"], reference_path_m=locs,
        )
        assert m.success and m.ndtw == 1.0 and m.ne_m < 0.6 and 0.85 < m.spl <= 1.0
        # The start alone (agent never moved) is scored against the same reference: nDTW < 1.
        m0 = episode_metrics(locs[:1], goal, geodesic=euclidean_geodesic, stop_called=True, reference_path_m=locs)
        assert m0.ndtw < 1.0
