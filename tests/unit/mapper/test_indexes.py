"""The mapper's incremental indexes answer what a plain search over everything answers.

Exploration asks "which nodes of this status are near here", "the visited nodes", "the walked
graph" and "mark this scan's cells" tens of thousands of times at 1,000 m2; the indexes that make
those cheap must never change an answer (the explored graph must stay the same)."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np

from services.mapper.core.frontier import CHUNK, FreeSpaceMap, FrontierConfig
from services.mapper.core.navgraph import GridGraph, NodeStatus


def _random_graph(seed: int) -> GridGraph:
    rng = np.random.default_rng(seed)
    g = GridGraph()
    visited: list[str] = []
    for k in range(400):
        p = np.append(rng.uniform(-6, 6, 2), rng.choice([0.0, 2.8]))
        if rng.random() < 0.4:
            n = g.add_visited(p, order=k)
            if visited and rng.random() < 0.8:
                g.connect(visited[int(rng.integers(len(visited)))], n, float(rng.uniform(0.2, 3.0)))
            visited.append(n)
        elif visited:
            n = g.add_observed(p, visited[-1], 0.5)
            if n is not None and rng.random() < 0.5:
                g.set_status(n, NodeStatus.COVERED if rng.random() < 0.5 else NodeStatus.UNREACHABLE)
        if visited and rng.random() < 0.05 and g.g.number_of_edges():
            u, v = list(g.g.edges)[int(rng.integers(g.g.number_of_edges()))]
            g.remove_edge(u, v)
    return g


def test_near_and_nodes_with_answer_as_a_plain_search():
    rng = np.random.default_rng(7)
    for seed in range(3):
        g = _random_graph(seed)
        for st in [(), (NodeStatus.VISITED,), (NodeStatus.FRONTIER, NodeStatus.UNREACHABLE)]:
            assert g.nodes_with(*st or tuple(NodeStatus)) == [
                n for n, s in g.g.nodes(data="status") if s in (st or tuple(NodeStatus))]
        for _ in range(200):
            p = np.append(rng.uniform(-7, 7, 2), rng.choice([0.0, 0.3, 2.8]))
            r = float(rng.uniform(0.1, 2.5))
            for st in [(), (NodeStatus.VISITED,), (NodeStatus.FRONTIER,), (NodeStatus.COVERED, NodeStatus.VISITED)]:
                plain = sorted(n for n, a in g.g.nodes(data=True)
                               if (not st or a["status"] in st)
                               and math.hypot(a["pos"][0] - p[0], a["pos"][1] - p[1]) < r
                               and abs(a["pos"][2] - p[2]) < 0.4)
                assert g.near(p, r, 0.4, *st) == plain


def test_the_walked_graph_is_the_traversed_view_with_neighbours_in_the_same_order():
    for seed in range(3):
        g = _random_graph(seed)
        view, walked = g.traversed(), g.walked()
        assert set(walked.nodes) == set(view.nodes)
        assert {frozenset(e) for e in walked.edges} == {frozenset(e) for e in view.edges}
        for n in view.nodes:
            assert list(walked.adj[n]) == list(view.adj[n])  # the shortest paths' tie order
            for m in view.adj[n]:
                assert walked.edges[n, m]["length"] == view.edges[n, m]["length"]
        nodes = list(view.nodes)
        for a, b in zip(nodes[::7], nodes[3::7]):
            try:
                expected = nx.shortest_path(view, a, b, weight="length")
            except nx.NetworkXNoPath:
                expected = None
            try:
                got = nx.shortest_path(walked, a, b, weight="length")
            except nx.NetworkXNoPath:
                got = None
            assert got == expected


def _plain_scan_cells(m: FreeSpaceMap, position_m, heading_rad, obstacle_m):
    """The straightforward ray cast: every sample of every ray as one (rays, samples, 2) array."""
    c = m.cfg
    ang = heading_rad + m.angles_rad
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    seen = ~np.isnan(obstacle_m)
    rng = np.where(np.isfinite(obstacle_m), obstacle_m, c.max_range_m)
    mask = seen[:, None] & (m._samples[None, :] < (rng[:, None] - c.cell_m * 0.5))
    pts = position_m[None, None, :2] + dirs[:, None, :] * m._samples[None, :, None]
    free = np.floor(pts[mask] / c.cell_m).astype(np.int64)
    free = np.vstack([free, np.floor(position_m[None, :2] / c.cell_m).astype(np.int64)])
    hit = seen & np.isfinite(obstacle_m) & (obstacle_m < c.max_range_m)
    hpts = position_m[None, :2] + dirs * (np.where(hit, obstacle_m, 0.0)[:, None] + c.cell_m * 0.5)
    return {tuple(v) for v in free}, {tuple(v) for v in np.floor(hpts[hit] / c.cell_m).astype(np.int64)}


def _marked(store) -> set[tuple[int, int]]:
    return {(cx * CHUNK + i, cy * CHUNK + j) for (cx, cy), arr in store.items() for i, j in np.argwhere(arr)}


def test_a_scan_marks_the_cells_of_the_plain_ray_cast():
    rng = np.random.default_rng(3)
    angles = np.arange(360) * (2.0 * math.pi / 360)
    for _ in range(20):
        m = FreeSpaceMap(angles, FrontierConfig())
        pos = np.append(rng.uniform(-20, 20, 2), 0.0)  # chunk borders on both sides of zero
        obst = rng.uniform(0.05, 6.0, 360)
        obst[rng.random(360) < 0.2] = np.inf
        obst[rng.random(360) < 0.1] = np.nan
        heading = float(rng.uniform(-math.pi, math.pi))
        m.add_scan(pos, heading, obst)
        free, occ = _plain_scan_cells(m, pos, heading, obst)
        assert _marked(m.levels[0].free) == free
        assert _marked(m.levels[0].occ) == occ


def test_nearest_partitioned_node_is_networkxs_answer():
    """Regions: a stair or observed node takes the region of the partitioned node nearest over the
    walked edges (the smallest id among equally near ones): one scipy search for all of them gives
    what a networkx search per node gave."""
    from services.mapper.core.regions import _nearest_partitioned

    rng = np.random.default_rng(11)
    for seed in range(3):
        g = _random_graph(seed)
        visited = g.nodes_with(NodeStatus.VISITED)
        partitioned = {n: int(rng.integers(4)) for n in visited if rng.random() < 0.7}
        ask = _nearest_partitioned(g, g.g, partitioned)
        view = nx.Graph(g.traversed())
        for n in g.g.nodes:
            if n in partitioned:
                continue
            ref = g.g.nodes[n].get("parent") or n
            if ref in partitioned:
                continue
            try:
                lengths = nx.single_source_dijkstra_path_length(view, ref, weight="length")
                expected = partitioned[min((d, m) for m, d in lengths.items() if m in partitioned)[1]]
            except (ValueError, nx.NodeNotFound):
                expected = None
            assert ask(ref) == expected


def test_a_new_scan_is_never_answered_from_the_memo():
    """The map's analysis of a grid is kept for the next question about the same visited nodes
    (the narrow pass after the wide one); a scan in between must make it stale."""
    from tests.unit.mapper.test_frontier import ANGLES, corridor_scan

    m = FreeSpaceMap(ANGLES)
    start = np.array([0.0, 0.0, 0.0])
    m.add_scan(start, 0.0, corridor_scan(0.0, 12.0))
    nodes = [("a", start)]
    assert len(m.frontier_targets(0.0, nodes, exclude_radius_m=0.8)) == 1
    assert len(m.frontier_targets(0.0, nodes, exclude_radius_m=0.8, body_radius_m=0.1)) == 1
    for x in range(4, 12):  # someone else walks the corridor to its closed end
        p = np.array([float(x), 0.0, 0.0])
        m.add_scan(p, 0.0, corridor_scan(p[0], 12.0))
    assert m.frontier_targets(0.0, nodes, exclude_radius_m=0.8) == []
