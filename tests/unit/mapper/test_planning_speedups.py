"""The planning speed-ups give what the plain algorithms give: the lazy greedy set cover picks the
same hubs as re-scoring every set each step, the stencil visibility agrees with a per-ray march,
the limited hub searches equal unlimited Dijkstra, the chunked occupancy equals the all-at-once
one, and the hub order is never longer than nearest neighbour."""

import math

import numpy as np
import pytest
from scipy.sparse.csgraph import dijkstra

from services.mapper.core.occupancy import FREE, OCCUPIED, OccupancyGrid, build_occupancy
from services.mapper.core.tours import (
    _hub_paths,
    greedy_set_cover,
    grid_graph,
    nearest_neighbour_order,
    plan_order,
    tour_cost,
    visibility_sparse,
)


def _greedy_rescoring(vis, tau, tie_break):
    """Reference: re-score every set at every step (argmax, first index on ties)."""
    m = vis.astype(np.float64)
    unc = np.ones(vis.shape[1])
    tb = tie_break / (np.max(tie_break) + 1e-9)
    chosen, cov = [], 0.0
    while cov < tau:
        gain = m @ unc
        best = int(np.argmax(gain + 0.5 * tb * (gain > 0)))
        if gain[best] <= 0:
            break
        chosen.append(best)
        unc *= 1.0 - m[best]
        cov = 1.0 - unc.sum() / vis.shape[1]
    return chosen, cov


@pytest.mark.parametrize("seed", range(6))
def test_lazy_greedy_set_cover_picks_what_rescoring_picks(seed):
    rng = np.random.default_rng(seed)
    n_s, n_t = rng.integers(5, 80), rng.integers(20, 600)
    vis = rng.random((n_s, n_t)) < rng.uniform(0.02, 0.3)
    vis[rng.integers(n_s)] = vis[rng.integers(n_s)]  # duplicate rows: exact ties on gain
    tb = np.round(rng.random(n_s), 1)  # and ties on the tie-break
    for tau in (0.5, 0.9, 1.0):
        assert greedy_set_cover(vis, tau, tb) == _greedy_rescoring(vis, tau, tb)


def _march_visibility(occ, hubs, targets, radius_m, rays):
    """Reference: one ray march per hub in metres, each target judged on its nearest ray."""
    cell = occ.cell_m
    step = cell * 0.5
    samples = np.arange(step, radius_m + step, step)
    nx_, ny_ = occ.cells.shape
    out = np.zeros((len(hubs), len(targets)), dtype=bool)
    for k, h in enumerate((hubs + 0.5) * cell):
        first = np.full(rays, np.inf)
        for a in range(rays):
            ang = a * 2 * math.pi / rays
            for s in samples:
                i, j = (int(math.floor((h[0] + math.cos(ang) * s) / cell)),
                        int(math.floor((h[1] + math.sin(ang) * s) / cell)))
                if not (0 <= i < nx_ and 0 <= j < ny_) or occ.cells[i, j] == OCCUPIED:
                    first[a] = s
                    break
        for t, q in enumerate((targets + 0.5) * cell):
            d = q - h
            r = math.hypot(*d)
            a = int(math.floor((math.atan2(d[1], d[0]) % (2 * math.pi)) / (2 * math.pi) * rays + 0.5)) % rays
            out[k, t] = r <= radius_m + 1e-9 and r <= first[a] + cell * 0.75
    return out


def _rooms():
    cells = np.full((60, 40), FREE, np.uint8)
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = OCCUPIED
    cells[30, :] = OCCUPIED
    cells[30, 15:22] = FREE  # a door
    cells[10:14, 10:30] = OCCUPIED  # a table
    return OccupancyGrid(cells, np.zeros(2), 0.1, 0.0)


def test_stencil_visibility_agrees_with_a_ray_march():
    occ = _rooms()
    free = np.argwhere(occ.free)
    rng = np.random.default_rng(0)
    hubs = free[rng.choice(len(free), 6, replace=False)]
    ref = _march_visibility(occ, hubs, free, 2.0, 72)
    got = visibility_sparse(occ, hubs, free, 2.0, 72, batch=4).toarray()  # batches of hubs too
    # Only cells whose sample lands exactly on a cell edge may differ (rounding).
    assert np.sum(got != ref) <= 0.002 * ref.size
    assert got.sum() > 0.05 * ref.size


def test_hub_paths_equal_unlimited_dijkstra_around_a_long_wall():
    # Two hubs 0.6 m apart on either side of a long wall: the path around is ~8 m, far beyond the
    # first distance limit, so the limited search has to be redone.
    mask = np.ones((80, 20), dtype=bool)
    mask[5:80, 9:11] = False
    g, flat = grid_graph(mask, 0.1)
    lookup = {f: k for k, f in enumerate(flat)}
    cells = np.array([[60, 6], [60, 13], [20, 5]])
    hubs = np.array([lookup[np.ravel_multi_index(tuple(c), mask.shape)] for c in cells])
    entry = lookup[np.ravel_multi_index((2, 2), mask.shape)]
    dist, pred = _hub_paths(g, hubs, cells, 0.1, entry)
    ref, ref_pred = dijkstra(g, indices=hubs, return_predecessors=True)
    assert np.allclose(dist[:, hubs], ref[:, hubs])
    assert np.allclose(dist[:, entry], ref[:, entry])
    assert dist[0, hubs[1]] > 10.0  # really around the wall
    # The predecessor chains walk the same length.
    node, walked = hubs[1], 0.0
    while node != hubs[0]:
        prev = pred[0, node]
        walked += g[prev, node]
        node = prev
    assert walked == pytest.approx(ref[0, hubs[1]])


@pytest.mark.parametrize("seed", range(8))
def test_hub_order_is_never_longer_than_nearest_neighbour(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 25))
    pts = rng.random((n, 2)) * 20
    length = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    penalty = rng.random((n, n)) * 6.0  # the overlap term pulls the order away from pure length
    cost = length + (penalty + penalty.T) / 2
    np.fill_diagonal(cost, 0.0)
    order = plan_order(cost, length, 0)
    assert order[0] == 0 and sorted(order) == list(range(n))
    assert tour_cost(order, length) <= tour_cost(nearest_neighbour_order(length, 0), length) + 1e-9


def test_chunked_occupancy_equals_one_chunk():
    rng = np.random.default_rng(3)
    n, angles = 40, np.arange(90) * (2 * math.pi / 90)
    pos = np.column_stack([rng.uniform(0, 6, n), rng.uniform(0, 4, n), np.zeros(n)])
    obst = rng.uniform(0.3, 6.0, (n, len(angles)))
    obst[rng.random(obst.shape) < 0.1] = np.inf
    obst[rng.random(obst.shape) < 0.05] = np.nan
    heads = rng.uniform(-math.pi, math.pi, n)
    one = build_occupancy(pos, obst, angles, heads, 0.0, chunk_samples=10**9)
    many = build_occupancy(pos, obst, angles, heads, 0.0, chunk_samples=1)  # one scan at a time
    assert np.array_equal(one.cells, many.cells)
    assert (one.cells == FREE).sum() > 1000 and (one.cells == OCCUPIED).sum() > 100
