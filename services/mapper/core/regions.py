"""From an exploration to a scene map: floors, stairs, occupancy per floor, Louvain regions.

Stairs are found the way the paper says: runs of consecutive vertical moves along the robot's
trajectory. Floors are the heights where visited nodes pile up. Each floor's nodes are partitioned
into regions by Louvain community detection (networkx, seeded). The traversed edges of a DFS form
(almost) a tree, on which modularity has little to grip, so the partition graph also joins visited
nodes that see each other (line of sight on the explored occupancy, within ``link_radius_m``):
rooms become dense clusters and doorways the sparse cuts between them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import networkx as nx
import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import ConvexHull, QhullError

from services.mapper.core.explorer import ExplorationResult
from services.mapper.core.navgraph import NodeStatus
from services.mapper.core.occupancy import OccupancyGrid, build_occupancy, line_of_sight

log = logging.getLogger(__name__)


class RegionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    floor_gap_m: float = Field(0.3, gt=0.0)  # heights closer than this are one level
    # A level is a floor only with enough nodes spread over enough area: a stairwell landing or a
    # pause on the flight is not one (stair-run nodes are left out before levels are counted).
    floor_min_nodes: int = Field(5, ge=1)
    floor_min_area_m2: float = Field(6.0, ge=0.0)  # convex hull of the level's nodes
    stair_min_rise_m: float = Field(0.1, gt=0.0)  # a move rising this much is vertical
    stair_min_total_m: float = Field(0.5, gt=0.0)  # a run of vertical moves this tall is stairs
    occupancy_cell_m: float = Field(0.1, gt=0.0)
    sensor_range_m: float = Field(5.0, gt=0.0)
    link_radius_m: float = Field(3.0, gt=0.0)
    louvain_resolution: float = Field(1.0, gt=0.0)
    min_region_nodes: int = Field(3, ge=1)
    seed: int = 0


@dataclass
class Floor:
    index: int
    z_m: float
    occupancy: OccupancyGrid
    nodes: list[str]  # visited, non-stair nodes on this floor


@dataclass
class SceneMap:
    """What the tour planner works on."""

    result: ExplorationResult
    floors: list[Floor]
    stairs: set[str]
    regions: dict[int, list[str]]  # region id -> visited node ids
    region_floor: dict[int, int]
    node_region: dict[str, int] = field(default_factory=dict)
    # The exploration's map <- odom localiser (localise.Localiser), when it ran one: the tours go on
    # correcting the robot's odometry with it, so they reach the hubs the graph placed.
    localiser: Any = None


def detect_floors(
    z_m: np.ndarray,
    gap_m: float,
    min_nodes: int,
    xy_m: np.ndarray | None = None,
    min_area_m2: float = 0.0,
) -> list[float]:
    """Levels where heights pile up: single-linkage clusters of sorted z, big enough ones kept.

    With ``xy_m`` (N, 2) a level must also spread over ``min_area_m2`` (convex hull of its nodes).
    When no cluster qualifies the most populated one is the only floor.
    """
    z = np.asarray(z_m, dtype=np.float64)
    if len(z) == 0:
        return []
    order = np.argsort(z, kind="stable")
    zs = z[order]
    splits = np.nonzero(np.diff(zs) > gap_m)[0] + 1
    groups = np.split(order, splits)
    levels = []
    for grp in groups:
        if len(grp) < min_nodes:
            continue
        if xy_m is not None and min_area_m2 > 0 and _hull_area(np.asarray(xy_m)[grp]) < min_area_m2:
            continue
        levels.append(float(np.median(z[grp])))
    if not levels:
        biggest = max(groups, key=len)
        levels = [float(np.median(z[biggest]))]
    return levels


def _hull_area(xy: np.ndarray) -> float:
    if len(xy) < 3:
        return 0.0
    try:
        return float(ConvexHull(xy).volume)  # a 2-D hull's "volume" is its area
    except QhullError:
        return 0.0  # collinear nodes: a corridor one node wide has no area to speak of


def detect_stair_positions(trajectory_m: np.ndarray, min_rise_m: float, min_total_m: float) -> np.ndarray:
    """Positions (N, 3) on runs of consecutive vertical moves whose total rise is stair-like."""
    traj = np.asarray(trajectory_m, dtype=np.float64)
    if len(traj) < 2:
        return np.zeros((0, 3))
    dz = np.diff(traj[:, 2])
    sign = np.where(dz >= min_rise_m, 1, np.where(dz <= -min_rise_m, -1, 0))
    out = []
    k = 0
    while k < len(sign):
        if sign[k] == 0:
            k += 1
            continue
        j = k
        while j + 1 < len(sign) and sign[j + 1] == sign[k]:
            j += 1
        if abs(traj[j + 1, 2] - traj[k, 2]) >= min_total_m:
            out.append(traj[k : j + 2])
        k = j + 1
    return np.concatenate(out) if out else np.zeros((0, 3))


def analyse(result: ExplorationResult, config: RegionConfig | None = None) -> SceneMap:
    """Floors, stairs, occupancy and regions of an exploration; annotates the graph's nodes."""
    cfg = config or RegionConfig()
    gg = result.graph
    g = gg.g
    visited = gg.nodes_with(NodeStatus.VISITED)
    vpos = gg.positions(visited)
    stair_pts = detect_stair_positions(result.trajectory_m, cfg.stair_min_rise_m, cfg.stair_min_total_m)
    on_run = np.zeros(len(visited), dtype=bool)
    if len(stair_pts) and len(vpos):
        d = np.linalg.norm(vpos[:, None, :] - stair_pts[None, :, :], axis=2)
        on_run = d.min(axis=1) < gg.dxy_m
    # Stair-run nodes first out, then the levels: a pause on the flight never makes a floor.
    keep = ~on_run if (~on_run).any() else np.ones(len(vpos), dtype=bool)
    levels = detect_floors(vpos[keep, 2], cfg.floor_gap_m, cfg.floor_min_nodes,
                           vpos[keep, :2], cfg.floor_min_area_m2) if len(vpos) else [0.0]

    stairs: set[str] = set()
    if len(vpos):
        dist = np.abs(vpos[:, 2:3] - np.array(levels)[None, :])
        nearest = dist.argmin(axis=1)
        off_floor = dist.min(axis=1) > cfg.floor_gap_m
        lv = np.array(levels)
        for k, nid in enumerate(visited):
            f = int(nearest[k])
            g.nodes[nid]["floor"] = f
            # A node on a stair run that still stands at a floor's height is a landing, not stairs.
            at_level = abs(vpos[k, 2] - lv[f]) <= cfg.floor_gap_m / 2
            is_stair = bool(off_floor[k] or (on_run[k] and not at_level))
            g.nodes[nid]["stairs"] = is_stair
            if is_stair:
                stairs.add(nid)

    angles = result.scan_angles_rad
    floors: list[Floor] = []
    for fi, z in enumerate(levels):
        # Scans taken on the flight see the stairwell as walkable ground of this floor: left out.
        scans = [s for s in result.scans
                 if abs(s.position_m[2] - z) <= cfg.floor_gap_m and s.node not in stairs]
        if scans:
            occ = build_occupancy(
                np.stack([s.position_m for s in scans]),
                np.stack([s.obstacle_m for s in scans]),
                angles,
                np.array([s.heading_rad for s in scans]),
                floor_z_m=z,
                cell_m=cfg.occupancy_cell_m,
                max_range_m=cfg.sensor_range_m,
            )
        else:
            occ = build_occupancy(np.zeros((0, 3)), np.zeros((0, len(angles))), angles,
                                  np.zeros(0), z, cfg.occupancy_cell_m, cfg.sensor_range_m)
        nodes = [n for n in visited if g.nodes[n].get("floor") == fi and n not in stairs]
        floors.append(Floor(fi, z, occ, nodes))

    regions: dict[int, list[str]] = {}
    region_floor: dict[int, int] = {}
    for fl in floors:
        for comm in _partition(gg, fl, cfg):
            rid = len(regions)
            regions[rid] = sorted(comm)
            region_floor[rid] = fl.index
    node_region = {n: r for r, ns in regions.items() for n in ns}
    # Stair nodes and observed nodes take the region of their nearest partitioned neighbour (one
    # search per such neighbour, shared by every node seen from it: a flight's candidates are many).
    partitioned = dict(node_region)
    nearest = _nearest_partitioned(gg, g, partitioned)
    for n in g.nodes:
        if n in node_region:
            continue
        ref = g.nodes[n].get("parent") or n
        r = node_region.get(ref)
        if r is None and ref in g:
            r = nearest(ref)
        if r is not None:
            node_region[n] = r
    for n in g.nodes:
        g.nodes[n]["region"] = node_region.get(n)
        if "floor" not in g.nodes[n] and node_region.get(n) is not None:
            g.nodes[n]["floor"] = region_floor[node_region[n]]
    log.info("%d floors, %d stair nodes, %d regions", len(floors), len(stairs), len(regions))
    return SceneMap(result, floors, stairs, regions, region_floor, node_region)


def _nearest_partitioned(gg, g: nx.Graph, partitioned: dict[str, int]):
    """ref -> the region of the partitioned node nearest to ``ref`` over the traversed edges (the
    smallest id among equally near ones), None when none is reachable or ``ref`` is not visited.

    The searches run as one multi-source Dijkstra (scipy) from every node that may ask, before the
    first question: a networkx search per stair node took 1.4 s of 2.2 at 1,000 m2 on three floors.
    The lengths are the same sums along the same shortest paths, so the answers are networkx's."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    asking = sorted({ref for n in g.nodes if n not in partitioned
                     for ref in [g.nodes[n].get("parent") or n] if ref not in partitioned and ref in g})
    walked = gg.walked()
    index = {n: k for k, n in enumerate(walked.nodes)}
    sources = [r for r in asking if r in index]
    answers: dict[str, int | None] = dict.fromkeys(asking)
    if sources and partitioned:
        e = list(walked.edges(data="length"))
        u = np.array([index[a] for a, _, _ in e], dtype=np.int64)
        v = np.array([index[b] for _, b, _ in e], dtype=np.int64)
        w = np.array([x for _, _, x in e], dtype=np.float64)
        m = len(index)
        csr = coo_matrix((np.r_[w, w], (np.r_[u, v], np.r_[v, u])), shape=(m, m)).tocsr()
        dist = dijkstra(csr, directed=True, indices=[index[r] for r in sources])
        cols = [index[n] for n in partitioned if n in index]
        names = np.array([n for n in partitioned if n in index])
        sub = dist[:, cols]
        for k, ref in enumerate(sources):
            d = sub[k]
            if not np.isfinite(d).any():
                continue
            best = min(names[d == d.min()])
            answers[ref] = partitioned[str(best)]
    return answers.get


def _partition(gg, fl: Floor, cfg: RegionConfig) -> list[set[str]]:
    nodes = fl.nodes
    if not nodes:
        return []
    if len(nodes) < 2 * cfg.min_region_nodes:
        return [set(nodes)]
    pos = gg.positions(nodes)
    occ = fl.occupancy
    idx = occ.to_index(pos)
    pg = nx.Graph()
    pg.add_nodes_from(nodes)
    for u, v, d in gg.g.subgraph(nodes).edges(data=True):
        pg.add_edge(u, v, weight=1.0 / (0.5 + d["length"]))
    iu, ju = np.triu_indices(len(nodes), k=1)
    dd = np.linalg.norm(pos[iu, :2] - pos[ju, :2], axis=1)
    close = dd <= cfg.link_radius_m
    iu, ju, dd = iu[close], ju[close], dd[close]
    if len(iu):
        los = line_of_sight(occ.occupied, idx[iu], idx[ju])
        for a, b, d in zip(iu[los], ju[los], dd[los], strict=True):
            w = 1.0 / (0.5 + d)
            if pg.has_edge(nodes[a], nodes[b]):
                w += pg.edges[nodes[a], nodes[b]]["weight"]
            pg.add_edge(nodes[a], nodes[b], weight=w)
    comms = [set(c) for c in nx.community.louvain_communities(
        pg, weight="weight", resolution=cfg.louvain_resolution, seed=cfg.seed)]
    # Tiny communities (a node in a doorway) join the neighbour they are most tied to.
    comms.sort(key=len)
    changed = True
    while changed and len(comms) > 1:
        changed = False
        for c in comms:
            if len(c) >= cfg.min_region_nodes:
                continue
            best, best_w = None, 0.0
            for other in comms:
                if other is c:
                    continue
                w = sum(pg.edges[u, v]["weight"] for u in c for v in pg[u] if v in other)
                if w > best_w:
                    best, best_w = other, w
            if best is not None:
                best |= c
                comms.remove(c)
                changed = True
                break
    comms.sort(key=lambda c: min(gg.g.nodes[n]["order"] for n in c))
    return comms
