"""Visibility-aware tour planning per region (paper 4.1, Algorithm 1, step 2).

For each region: reachable cells (explored free space with at least ``clearance`` to anything
occupied or unknown) downsampled on a 1 m grid give candidate hubs; ``Vis(h)`` is the set of the
region's explored cells within ``vis_radius_m`` that ``h`` sees (line of sight on the occupancy);
a greedy set cover picks hubs until ``tau`` of the region is covered; 2-opt orders them into a
Hamiltonian cycle under ``C(u, v) = L(u, v) + lambda_overlap * (1 - IoU(Vis u, Vis v))``, with
``L`` the shortest path length over the reachable cells. The dense path between hubs follows those
cells, so it keeps the clearance by construction, and is then shortcut where line of sight on the
reachable cells allows (string pulling) and resampled.
"""

from __future__ import annotations

import heapq
import logging
import math
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage, sparse
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from shared.geometry import wrap_angle
from shared.schemas import Pose, Tour

from services.mapper.core.errors import PlanningError
from services.mapper.core.occupancy import OCCUPIED, OccupancyGrid, line_of_sight
from services.mapper.core.regions import SceneMap

log = logging.getLogger(__name__)


class TourConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    hub_grid_m: float = Field(1.0, gt=0.0)
    vis_radius_m: float = Field(3.0, gt=0.0)
    # A robot that declares depth noise (``Panorama.depth_noise_rel``: sigma = rel * depth^2) records
    # well only what it looks at from near: a hub sees a cell only as far as that sigma stays within
    # this (0.01 * depth^2, the noisy row's sensor: 2.5 m for 0.0625 m). Noise-free, ``vis_radius_m``.
    max_depth_sigma_m: float = Field(0.0625, gt=0.0, le=1.0)
    tau: float = Field(0.9, gt=0.0, le=1.0)
    lambda_overlap: float = Field(1.0, ge=0.0)  # metres of path one unit of (1 - IoU) is worth
    body_radius_m: float = Field(0.2, ge=0.0)
    clearance_margin_m: float = Field(0.1, ge=0.0)
    vis_rays: int = Field(360, ge=36, le=2048)
    path_step_m: float = Field(0.25, gt=0.0)
    close_loop: bool = True  # return to the start hub: a loop closure for the reconstruction
    # Where hubs stand and paths run. "map": the scans' free cells with ``clearance_m`` (paths
    # string-pulled across them). "walked": only where the robot itself stood and moved during
    # exploration: hubs are its poses and paths follow its own moves, pose to pose. A real scan's
    # clutter (desk edges, chair legs, cables) is partly below or between the scanner's rays, and
    # 31 % of Replica office0's map-planned path samples stood where the simulator's agent cannot.
    paths_on: Literal["map", "walked"] = "map"
    walked_merge_m: float = Field(0.05, gt=0.0)  # poses this close are one place of the walk graph
    # "map" planning, a region at a time, falls back on the walk. A drifting robot's scans narrow the
    # doorways it walked through (one jamb seen from two poses that disagree by centimetres), so the
    # map's reachable cells split a region and its tour stands in one piece only: generated:0 with
    # the noisy robot at 1x planned three of its ten regions with hubs that together saw 57-62 % of
    # the region (the white desk of a bedroom was never recorded, and missions that named it went to
    # another room). Where the map's candidate hubs see less than this share of the region, or the
    # map plans no tour at all, the region is planned again on the robot's own walk, which it has
    # crossed, and the plan that covers more of the region is kept. The split regions' shares were
    # 0.06-0.78 on generated:0 and generated:3:floors=2 (noisy, 1x); those houses' noise-free
    # explorations are at 0.87 and above but one (0.67, which the walk covers no better), so their tours
    # and maps stay as they were. Elsewhere a noise-free region can fall back too (4 of bench.ablation's
    # 15 houses changed map, its SR on them did not). 0: never.
    walked_fallback_below: float = Field(0.8, ge=0.0, le=1.0)
    max_2opt_rounds: int = Field(200, ge=0)
    # How far either side of the heading a hub is reached with the look-around records: the robot's
    # yaw sweep (+-60 deg, the paper's) plus half its camera's hfov (90 deg). A one-hub tour has no
    # path to set that heading, so it faces where this window holds most of what the hub sees:
    # facing east whatever the room, generated:1001:floors=2's bathroom hub (noisy, 1x) never
    # recorded the toilet 149 deg off east of it, which the set cover counted as seen (now it faces
    # -105 deg: 0 -> 1612 map points within 0.5 m of the toilet). Objects with >= 50 points of their
    # label in their box, noise-free maps of generated:1001:floors=2, 1004, 0 and 3:floors=2: 226 -> 228
    # of 240. A hub that faces its own region's cells can turn away from a neighbour's object it caught
    # by chance (generated:3:floors=2's living-room tv): the sweep's 210 deg is the limit, not this.
    look_around_half_fov_deg: float = Field(105.0, gt=0.0, le=180.0)

    @property
    def clearance_m(self) -> float:
        return self.body_radius_m + self.clearance_margin_m

    def vis_radius_for(self, depth_noise_rel: float) -> float:
        """How far a hub sees for a sensor of this declared depth noise (0: exact)."""
        if depth_noise_rel <= 0.0:
            return self.vis_radius_m
        return min(self.vis_radius_m, math.sqrt(self.max_depth_sigma_m / depth_noise_rel))


@dataclass
class PlannedTour:
    """A tour plus what the executor and the benchmark need beyond the bus message."""

    tour: Tour
    hub_path_index: list[int]  # index into tour.path_m of each hub, in visiting order
    length_m: float  # refined path length
    nn_length_m: float  # plain nearest-neighbour cycle over the same hubs, by L
    order_length_m: float  # the 2-opt cycle by L (comparable to nn_length_m)
    achievable_coverage: float  # what every candidate hub together would cover
    plan_s: float  # set cover + 2-opt time
    candidates: int
    paths_on: str = "map"  # what the hubs and paths were planned on (TourConfig.paths_on, or its fallback)


# --- pieces (public so that tests and benchmarks can call them on their own) --------------------


def grid_graph(mask: np.ndarray, cell_m: float) -> tuple[sparse.csr_matrix, np.ndarray]:
    """8-connected graph over the True cells of ``mask``; returns (csr, flat index -> node id)."""
    nx_, ny_ = mask.shape
    ids = np.full(mask.size, -1, dtype=np.int64)
    flat = np.flatnonzero(mask.ravel())
    ids[flat] = np.arange(len(flat))
    ids = ids.reshape(mask.shape)
    rows, cols, w = [], [], []
    for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
        i0, i1 = max(0, -di), nx_ - max(0, di)
        j0, j1 = max(0, -dj), ny_ - max(0, dj)
        a = ids[i0:i1, j0:j1]
        b = ids[i0 + di : i1 + di, j0 + dj : j1 + dj]
        ok = (a >= 0) & (b >= 0)
        if di and dj:
            # No diagonal squeeze between two blocked corner cells.
            ok &= (ids[i0 + di : i1 + di, j0:j1] >= 0) & (ids[i0:i1, j0 + dj : j1 + dj] >= 0)
        rows.append(a[ok])
        cols.append(b[ok])
        w.append(np.full(int(ok.sum()), cell_m * math.hypot(di, dj)))
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    ww = np.concatenate(w)
    n = len(flat)
    m = sparse.coo_matrix((np.concatenate([ww, ww]), (np.concatenate([r, c]), np.concatenate([c, r]))), shape=(n, n))
    return m.tocsr(), flat


def _ray_offsets(cell_m: float, radius_m: float, rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell offsets (rays, S) of the ray-march samples from a cell centre, and the samples' ranges.

    Every hub stands at a cell centre, so the cells a ray from it crosses are the same offsets for
    every hub: computed once, then each hub's march is one gather.
    """
    step = cell_m * 0.5
    samples = np.arange(step, radius_m + step, step)
    ang = np.arange(rays) * (2.0 * math.pi / rays)
    di = np.floor(0.5 + np.cos(ang)[:, None] * samples[None, :] / cell_m).astype(np.int64)
    dj = np.floor(0.5 + np.sin(ang)[:, None] * samples[None, :] / cell_m).astype(np.int64)
    return di, dj, samples


def _disk_stencil(cell_m: float, radius_m: float, rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cell offsets within ``radius_m`` of a cell, with their range (m) and the ray they lie on."""
    r_cells = int(math.ceil(radius_m / cell_m))
    di, dj = np.mgrid[-r_cells : r_cells + 1, -r_cells : r_cells + 1]
    di, dj = di.ravel(), dj.ravel()
    r = cell_m * np.hypot(di, dj)
    keep = r <= radius_m + 1e-9  # a cell exactly at the radius is in, whatever the rounding
    di, dj, r = di[keep], dj[keep], r[keep]
    a = np.floor((np.arctan2(dj, di) % (2 * math.pi)) / (2 * math.pi) * rays + 0.5).astype(np.int64) % rays
    return di, dj, r, a


def visibility_sparse(
    occ: OccupancyGrid,
    hubs_idx: np.ndarray,
    targets_idx: np.ndarray,
    radius_m: float,
    rays: int = 360,
    batch: int = 64,
) -> sparse.csr_matrix:
    """(H, T) sparse bool: target cell t visible from hub h (within radius, no occupied cell between).

    ``rays`` rays are marched from each hub to the first occupied cell (or the grid's edge); a
    target within the radius is seen when it lies no farther than that first hit on its own ray
    (plus the half cell in which the ray stopped: a wall cell itself is seen). Only the cells of the
    disk around each hub are looked at, so the cost is hubs x disk, not hubs x region.
    """
    hubs_idx = np.asarray(hubs_idx, dtype=np.int64).reshape(-1, 2)
    targets_idx = np.asarray(targets_idx, dtype=np.int64).reshape(-1, 2)
    n_h, n_t = len(hubs_idx), len(targets_idx)
    if n_h == 0 or n_t == 0:
        return sparse.csr_matrix((n_h, n_t), dtype=bool)
    cell = occ.cell_m
    di, dj, samples = _ray_offsets(cell, radius_m, rays)
    sdi, sdj, sr, sa = _disk_stencil(cell, radius_m, rays)
    pad = int(max(np.abs(di).max(), np.abs(dj).max(), np.abs(sdi).max())) + 1
    # The window of the grid the hubs' rays and disks can touch (a region's, not the floor's);
    # outside the grid counts as blocked, as in a march that stops at the edge.
    w0 = hubs_idx.min(axis=0) - pad
    w1 = hubs_idx.max(axis=0) + pad + 1
    g0 = np.maximum(w0, 0)
    g1 = np.minimum(w1, occ.cells.shape)
    blocked = np.ones(w1 - w0, dtype=bool)
    blocked[g0[0] - w0[0] : g1[0] - w0[0], g0[1] - w0[1] : g1[1] - w0[1]] = (
        occ.cells[g0[0] : g1[0], g0[1] : g1[1]] == OCCUPIED)
    ny_p = blocked.shape[1]
    lookup = np.full(blocked.shape, -1, dtype=np.int64)
    tin = np.nonzero(np.all((targets_idx >= w0) & (targets_idx < w1), axis=1))[0]
    lookup[targets_idx[tin, 0] - w0[0], targets_idx[tin, 1] - w0[1]] = tin
    hubs_idx = hubs_idx - w0
    blocked, lookup = blocked.ravel(), lookup.ravel()
    ray_off = di * ny_p + dj  # (rays, S) flat offsets
    disk_off = sdi * ny_p + sdj  # (K,)
    seen_within = sr[None, :] - cell * 0.75  # target range minus the allowance
    rows, cols = [], []
    for b0 in range(0, n_h, batch):
        h = hubs_idx[b0 : b0 + batch]
        hflat = h[:, 0] * ny_p + h[:, 1]
        hit = blocked[hflat[:, None, None] + ray_off[None]]  # (B, rays, S)
        first = np.where(hit.any(axis=2), samples[np.argmax(hit, axis=2)], np.inf)  # (B, rays)
        tid = lookup[hflat[:, None] + disk_off[None, :]]  # (B, K)
        ok = (tid >= 0) & (seen_within <= first[:, sa])
        b, k = np.nonzero(ok)
        rows.append(b + b0)
        cols.append(tid[b, k])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    return sparse.csr_matrix((np.ones(len(r), dtype=bool), (r, c)), shape=(n_h, n_t))


def visibility(
    occ: OccupancyGrid,
    hubs_idx: np.ndarray,
    targets_idx: np.ndarray,
    radius_m: float,
    rays: int = 360,
) -> np.ndarray:
    """(H, T) bool: dense form of :func:`visibility_sparse`."""
    return visibility_sparse(occ, hubs_idx, targets_idx, radius_m, rays).toarray()


def greedy_set_cover(vis, tau: float, tie_break: np.ndarray | None = None) -> tuple[list[int], float]:
    """Pick sets (rows of ``vis``, dense or sparse bool) until ``tau`` of the columns are covered or
    no set adds any.

    Each step takes the set that adds the most uncovered columns; equal gains go to the larger
    ``tie_break`` (the hub's clearance), then to the lower index. A set's gain only shrinks as
    others are picked, so the gains sit in a heap and only the top one is re-counted (lazy greedy):
    the same picks as re-scoring every set at every step, at the cost of the rows actually touched.
    """
    m = sparse.csr_matrix(vis, dtype=bool)
    m.sum_duplicates()
    n_s, n_t = m.shape
    if n_t == 0 or n_s == 0:
        return [], 0.0
    tb = np.zeros(n_s) if tie_break is None else np.asarray(tie_break, dtype=np.float64) / (np.max(tie_break) + 1e-9)
    indptr, indices = m.indptr, m.indices
    size = np.diff(indptr)
    heap = [(-(float(size[i]) + 0.5 * tb[i]), i) for i in range(n_s) if size[i] > 0]
    heapq.heapify(heap)
    uncovered = np.ones(n_t, dtype=bool)
    left = n_t
    chosen: list[int] = []
    covered = 0.0
    while covered < tau and heap:
        _, i = heapq.heappop(heap)
        cols = indices[indptr[i] : indptr[i + 1]]
        gain = int(np.count_nonzero(uncovered[cols]))
        if gain == 0:
            continue
        key = (-(float(gain) + 0.5 * tb[i]), i)
        if heap and key > heap[0]:
            heapq.heappush(heap, key)  # stale: another set may now add more
            continue
        chosen.append(i)
        uncovered[cols] = False
        left -= gain
        covered = 1.0 - left / n_t
    return chosen, covered


def look_heading(standpoint_m: np.ndarray, targets_m: np.ndarray, half_window_rad: float, bins: int) -> float:
    """The heading (rad) from ``standpoint_m`` whose window of +-``half_window_rad`` holds the most
    of ``targets_m`` (the bearings binned into ``bins`` headings, the visibility's rays).

    0.0 where it holds as many as any (no target, a window all round, targets east): a start heading
    that cannot see more stays as it was. Otherwise the middle of the widest run of best headings,
    so that a few degrees of heading error at the hub do not drop a target at the window's edge."""
    d = np.asarray(targets_m, dtype=np.float64).reshape(-1, 3)[:, :2] - np.asarray(standpoint_m)[:2]
    step = 2.0 * math.pi / bins
    w = int(math.floor(half_window_rad / step + 1e-9))  # the window's half width in bins
    if len(d) == 0 or 2 * w + 1 >= bins:
        return 0.0
    hist = np.bincount(np.floor(np.arctan2(d[:, 1], d[:, 0]) / step + 0.5).astype(np.int64) % bins, minlength=bins)
    # held[k]: targets in bins k - w .. k + w (circular), a running sum over the histogram wrapped by w.
    run = np.concatenate([[0], np.cumsum(np.concatenate([hist[bins - w :], hist, hist[:w]]))])
    held = run[2 * w + 1 : 2 * w + 1 + bins] - run[:bins]
    best = held == held.max()
    if best[0]:
        return 0.0
    # Bin 0 is not among the best, so no run of best bins wraps round the end.
    edges = np.diff(np.concatenate([[0], best.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)  # runs [start, end)
    k = int(np.argmax(ends - starts))
    return float(wrap_angle(0.5 * (starts[k] + ends[k] - 1) * step))


def tour_cost(order: list[int] | np.ndarray, cost: np.ndarray, closed: bool = True) -> float:
    o = np.asarray(order)
    if len(o) < 2:
        return 0.0
    c = float(cost[o[:-1], o[1:]].sum())
    return c + (float(cost[o[-1], o[0]]) if closed else 0.0)


def nearest_neighbour_order(cost: np.ndarray, start: int = 0) -> list[int]:
    n = len(cost)
    order = [start]
    left = np.ones(n, dtype=bool)
    left[start] = False
    while left.any():
        c = np.where(left, cost[order[-1]], np.inf)
        nxt = int(np.argmin(c))
        order.append(nxt)
        left[nxt] = False
    return order


def two_opt(order: list[int], cost: np.ndarray, max_rounds: int = 200) -> list[int]:
    """Best-improvement 2-opt on a closed tour with a symmetric cost; the start stays first."""
    o = np.array(order)
    n = len(o)
    if n < 4:
        return list(o)
    for _ in range(max_rounds):
        a = o
        b = np.roll(o, -1)
        i, j = np.triu_indices(n, k=2)
        keep = ~((i == 0) & (j == n - 1))
        i, j = i[keep], j[keep]
        delta = cost[a[i], a[j]] + cost[b[i], b[j]] - cost[a[i], b[i]] - cost[a[j], b[j]]
        k = int(np.argmin(delta))
        if delta[k] >= -1e-9:
            break
        o = np.concatenate([o[: i[k] + 1], o[i[k] + 1 : j[k] + 1][::-1], o[j[k] + 1 :]])
    return list(o)


def plan_order(cost: np.ndarray, length: np.ndarray, start: int = 0, max_rounds: int = 200,
               closed: bool = True) -> list[int]:
    """The hub order: 2-opt under ``cost`` from the nearest-neighbour tour under ``cost`` and from
    the one under ``length``; the cheaper by ``cost`` of those not longer (by ``length``) than the
    nearest-neighbour tour under ``length``, which is the fallback. So the tour is never longer
    than the plain nearest-neighbour tour over the same hubs."""
    nn_len = nearest_neighbour_order(length, start)
    bound = tour_cost(nn_len, length, closed) + 1e-9
    options = [two_opt(nearest_neighbour_order(cost, start), cost, max_rounds), two_opt(nn_len, cost, max_rounds)]
    ok = [o for o in options if tour_cost(o, length, closed) <= bound]
    return min(ok, key=lambda o: tour_cost(o, cost, closed)) if ok else nn_len


def string_pull(cells: np.ndarray, blocked: np.ndarray) -> np.ndarray:
    """Drop path cells that a straight, unblocked segment can skip (greedy farthest visible)."""
    if len(cells) <= 2:
        return cells
    out = [0]
    k = 0
    while k < len(cells) - 1:
        cand = np.arange(len(cells) - 1, k, -1)
        ok = line_of_sight(blocked, np.repeat(cells[k][None], len(cand), 0), cells[cand])
        nxt = int(cand[np.argmax(ok)]) if ok.any() else k + 1
        out.append(nxt)
        k = nxt
    return cells[out]


def resample(points: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` along a polyline (ends kept)."""
    if len(points) < 2:
        return points
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return points[:1]
    t = np.unique(np.concatenate([np.arange(0.0, s[-1], step_m), [s[-1]]]))
    return np.column_stack([np.interp(t, s, points[:, d]) for d in range(points.shape[1])])


# --- the planner ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _FloorGrids:
    fflat: np.ndarray  # flat ids of the explored free cells
    region_of: np.ndarray  # their region (-1: none)
    clear: np.ndarray  # clearance per cell (m)
    reach: np.ndarray  # free with the tour's clearance
    rg: object  # the reachable cells' grid graph (csr)
    rflat: np.ndarray
    rcells: np.ndarray  # (N, 2) cell indices of the reachable cells (rflat unravelled)
    comp: np.ndarray  # connected component of each reachable cell
    rtree: cKDTree  # over rcells: snapping positions to reachable cells
    # "walked" planning: rg is the graph of the robot's own poses and moves, and these are the
    # poses (N, 2); None: rg is the reachable cells' grid graph.
    walked_xy: np.ndarray | None = None


class TourPlanner:
    def __init__(self, config: TourConfig | None = None):
        self.config = config or TourConfig()

    def plan(self, scene: SceneMap) -> list[PlannedTour]:
        """One tour per region (regions without any reachable cell are skipped with a warning)."""
        cfg = self.config
        tours = []
        grids: dict[tuple[int, bool], _FloorGrids] = {}  # per floor and kind, shared by its regions
        walked_default = cfg.paths_on == "walked"
        can_fall_back = not walked_default and cfg.walked_fallback_below > 0 and len(scene.result.trajectory_m) > 1
        for rid in sorted(scene.regions):
            pt, error = None, None
            try:
                pt = self.plan_region(scene, rid, grids, walked_default)
            except PlanningError as exc:
                error = exc
            if can_fall_back and (pt is None or pt.achievable_coverage < cfg.walked_fallback_below):
                try:
                    alt = self.plan_region(scene, rid, grids, walked=True)
                except PlanningError:
                    alt = None
                if alt is not None and (pt is None or alt.tour.coverage > pt.tour.coverage):
                    log.info("region %d: planned on the robot's walk (coverage %.2f; the map's: %s)", rid,
                             alt.tour.coverage, "none" if pt is None else f"{pt.tour.coverage:.2f}")
                    pt = alt
            if pt is None:
                log.warning("region %d: no tour: %s", rid, error)
            else:
                tours.append(pt)
        return tours

    def _floor_grids(self, scene: SceneMap, index: int, walked: bool) -> _FloorGrids:
        """What every region of a floor plans on: the explored cells' owner regions, clearance, the
        reachable-cell graph (``walked``: the robot's own walk), its components and a KD-tree over its
        cells. Built once per floor, not once per region, which kept planning quadratic in the floor's
        area."""
        cfg = self.config
        floor = scene.floors[index]
        occ = floor.occupancy
        g = scene.result.graph
        floor_nodes = floor.nodes
        fpos = g.positions(floor_nodes)
        # Every explored cell of the floor goes to the region of its nearest (geodesic) node.
        free = occ.free
        fg, fflat = grid_graph(free, occ.cell_m)
        fcells = np.column_stack(np.unravel_index(fflat, free.shape))
        node_cells = _cells_of(occ, fpos, cKDTree(fcells) if len(fcells) else None)
        ok = node_cells >= 0
        if not ok.any():
            raise PlanningError("no node of the floor lies on explored free space")
        _, _, src = dijkstra(fg, indices=node_cells[ok], min_only=True, return_predecessors=True)
        # Region of each source cell (of two nodes in one cell, the later one, as a dict would keep).
        cell_region = np.full(len(fflat), -1, dtype=np.int64)
        cell_region[node_cells[ok]] = [scene.node_region.get(floor_nodes[k], -1) for k in np.nonzero(ok)[0]]
        region_of = np.where(src >= 0, cell_region[np.maximum(src, 0)], -1)
        clear = occ.clearance_m()
        if walked:
            rg, walked_xy = walk_graph(scene.result.trajectory_m, floor.z_m, cfg.walked_merge_m)
            rcells = np.clip(occ.to_index(walked_xy), 0, np.array(free.shape) - 1)
            rflat = np.ravel_multi_index(rcells.T, free.shape)
            reach = np.zeros(free.shape, dtype=bool)
            reach.flat[rflat] = True
        else:
            # Reachable cells: free with clearance.
            walked_xy = None
            reach = free & (clear >= cfg.clearance_m)
            rg, rflat = grid_graph(reach, occ.cell_m)
            rcells = np.column_stack(np.unravel_index(rflat, reach.shape))
        _, comp = connected_components(rg, directed=False)
        return _FloorGrids(fflat, region_of, clear, reach, rg, rflat, rcells, comp,
                           cKDTree(rcells) if len(rcells) else None, walked_xy)

    def plan_region(self, scene: SceneMap, rid: int, grids: dict[tuple[int, bool], _FloorGrids] | None = None,
                    walked: bool | None = None) -> PlannedTour:
        """Region ``rid``'s tour, planned on the map's free cells or (``walked``; None: as
        ``paths_on`` says) on the robot's own walk."""
        cfg = self.config
        walked = cfg.paths_on == "walked" if walked is None else walked
        fi = scene.region_floor[rid]
        floor = scene.floors[fi]
        occ = floor.occupancy
        g = scene.result.graph
        nodes = scene.regions[rid]
        npos = g.positions(nodes)
        grids = {} if grids is None else grids
        if (fi, walked) not in grids:
            grids[fi, walked] = self._floor_grids(scene, fi, walked)
        fg_ = grids[fi, walked]
        free = occ.free
        target_flat = fg_.fflat[fg_.region_of == rid]
        if len(target_flat) == 0:
            raise PlanningError("region has no explored cell")
        targets = np.column_stack(np.unravel_index(target_flat, free.shape))
        clear, reach, rg, rflat, comp = fg_.clear, fg_.reach, fg_.rg, fg_.rflat, fg_.comp
        snap_m = cfg.clearance_m + 0.5
        rnode = _cells_of(occ, npos, fg_.rtree, snap_m=snap_m)
        if not (rnode >= 0).any():
            raise PlanningError("no region node has the required clearance")
        # One tour walks one connected piece of reachable space: the piece that holds most of the
        # region's nodes (a sliver cut off by furniture would need a hub the robot cannot reach).
        seeds = rnode[rnode >= 0]
        main = np.bincount(comp[seeds]).argmax()
        # Hubs stand in the region's own cells (walking slightly into a doorway is fine): the
        # region's cells dilated by two, in a window around the region rather than the whole floor.
        # Where none of them has the clearance (a room too narrow for the robot, or drawn so by a
        # drifting robot's scans: generated:3:floors=2 at 1x lost a region's tour so), a standpoint
        # as far outside it as a node may snap (its door, looking in) stands in; the visibility
        # below still decides whether it sees the region at all.
        rc = fg_.rcells
        for grow in (2, max(2, int(math.ceil(snap_m / occ.cell_m)))):
            lo = np.maximum(targets.min(axis=0) - grow, 0)
            hi = np.minimum(targets.max(axis=0) + grow + 1, free.shape)
            window = np.zeros(hi - lo, dtype=bool)
            window[targets[:, 0] - lo[0], targets[:, 1] - lo[1]] = True
            window = ndimage.binary_dilation(window, iterations=grow)
            inside = np.all((rc >= lo) & (rc < hi), axis=1)
            in_region = np.zeros(len(rflat), dtype=bool)
            in_region[inside] = window[rc[inside, 0] - lo[0], rc[inside, 1] - lo[1]]
            cand_nodes = np.nonzero((comp == main) & in_region)[0]
            if len(cand_nodes):
                break
        if len(cand_nodes) == 0:
            raise PlanningError("no reachable cell inside the region")
        cand_idx = rc[cand_nodes]
        hubs_c, hub_nodes = _voxel_downsample(occ, cand_idx, cand_nodes, clear, cfg.hub_grid_m)

        t0 = time.perf_counter()
        vis_radius_m = cfg.vis_radius_for(scene.result.depth_noise_rel)
        vis = visibility_sparse(occ, hubs_c, targets, vis_radius_m, cfg.vis_rays).tocsc()
        # Cells that no reachable standpoint sees (behind furniture, beyond a gap in a wall) cannot
        # be recorded by any tour: tau applies to the coverable cells, the coverage reported is of
        # all the region's cells.
        coverable = np.diff(vis.indptr) > 0
        achievable = float(coverable.mean())
        vis = vis[:, coverable].tocsr()
        chosen, rel = greedy_set_cover(vis, cfg.tau, clear[hubs_c[:, 0], hubs_c[:, 1]])
        coverage = rel * achievable
        if not chosen:
            raise PlanningError("no hub sees any cell of the region")
        hv = vis[chosen].astype(np.float32)
        hub_graph_nodes = hub_nodes[chosen]
        # Start at the hub nearest to where exploration first entered the region.
        first = min(nodes, key=lambda n: g.g.nodes[n]["order"])
        entry = int(_cells_of(occ, g.positions([first]), fg_.rtree, snap_m=snap_m)[0])
        if entry >= 0 and comp[entry] != main:
            entry = -1  # no hub is reachable from it: start at the first hub
        dist, pred = _hub_paths(rg, hub_graph_nodes, hubs_c[chosen], occ.cell_m, entry)
        lmat = dist[:, hub_graph_nodes]
        lmat = np.where(np.isfinite(lmat), lmat, 1e6)
        lmat = np.minimum(lmat, lmat.T)
        inter = (hv @ hv.T).toarray()
        sizes = np.asarray(hv.sum(axis=1)).ravel()
        iou = inter / np.maximum(sizes[:, None] + sizes[None, :] - inter, 1.0)
        cost = lmat + cfg.lambda_overlap * (1.0 - iou)
        np.fill_diagonal(cost, 0.0)
        start = int(np.argmin(dist[:, entry])) if entry >= 0 else 0
        nn = nearest_neighbour_order(lmat, start)
        order = plan_order(cost, lmat, start, cfg.max_2opt_rounds, cfg.close_loop)
        plan_s = time.perf_counter() - t0

        if fg_.walked_xy is None:
            path, hub_at = self._dense_path(order, hub_graph_nodes, pred, rflat, reach, occ)
            hubs_m = occ.centres(hubs_c[chosen][order])
        else:
            path, hub_at = self._walked_path(order, hub_graph_nodes, pred, fg_.walked_xy, floor.z_m)
            hubs_m = np.column_stack([fg_.walked_xy[hub_graph_nodes[order]], np.full(len(order), floor.z_m)])
        length = float(np.linalg.norm(np.diff(path[:, :2], axis=0), axis=1).sum()) if len(path) > 1 else 0.0
        heading = 0.0
        if len(path) > 1:
            d = path[1] - path[0]
            heading = math.atan2(d[1], d[0])
        elif len(chosen) == 1:
            seen = occ.centres(targets[coverable][vis[chosen[0]].indices])
            heading = look_heading(path[0], seen, math.radians(cfg.look_around_half_fov_deg), cfg.vis_rays)
        tour = Tour(
            region=rid,
            start_pose=Pose(position_m=tuple(float(v) for v in path[0]), heading_rad=heading),
            hubs_m=hubs_m,
            path_m=path,
            coverage=coverage,
        )
        return PlannedTour(
            tour=tour,
            hub_path_index=hub_at,
            length_m=length,
            nn_length_m=tour_cost(nn, lmat, cfg.close_loop),
            order_length_m=tour_cost(order, lmat, cfg.close_loop),
            achievable_coverage=achievable,
            plan_s=plan_s,
            candidates=len(hubs_c),
            paths_on="walked" if walked else "map",
        )

    def _dense_path(self, order, hub_nodes, pred, rflat, reach, occ):
        cfg = self.config
        blocked = ~reach
        seq = list(order) + ([order[0]] if cfg.close_loop and len(order) > 1 else [])
        pts: list[np.ndarray] = []
        hub_at: list[int] = []
        for k, h in enumerate(seq):
            if k == 0:
                pts.append(occ.centres(np.array([np.unravel_index(rflat[hub_nodes[h]], reach.shape)])))
                hub_at.append(0)
                continue
            prev = seq[k - 1]
            chain = [hub_nodes[h]]
            row = pred[prev]
            while chain[-1] != hub_nodes[prev] and chain[-1] >= 0:
                chain.append(row[chain[-1]])
            chain = chain[::-1]
            cells = np.column_stack(np.unravel_index(rflat[np.array(chain)], reach.shape))
            cells = string_pull(cells, blocked)
            seg = resample(occ.centres(cells), cfg.path_step_m)
            pts.append(seg[1:])
            if k < len(order):
                hub_at.append(sum(len(p) for p in pts) - 1)
        path = np.concatenate(pts) if pts else np.zeros((0, 3))
        return path, hub_at

    def _walked_path(self, order, hub_nodes, pred, xy, z_m):
        """The dense path over the walk graph: the robot's own poses from hub to hub, resampled
        along its own moves (nothing cut short: a shortcut is a line nobody walked)."""
        cfg = self.config
        seq = list(order) + ([order[0]] if cfg.close_loop and len(order) > 1 else [])
        pts: list[np.ndarray] = [np.array([[*xy[hub_nodes[seq[0]]], z_m]])]
        hub_at: list[int] = [0]
        for k in range(1, len(seq)):
            h, prev = seq[k], seq[k - 1]
            chain = [hub_nodes[h]]
            row = pred[prev]
            while chain[-1] != hub_nodes[prev] and chain[-1] >= 0:
                chain.append(row[chain[-1]])
            way = xy[np.array(chain[::-1])]
            seg = resample(np.column_stack([way, np.full(len(way), z_m)]), cfg.path_step_m)
            pts.append(seg[1:])
            if k < len(order):
                hub_at.append(sum(len(p) for p in pts) - 1)
        return np.concatenate(pts), hub_at


def walk_graph(trajectory_m: np.ndarray, floor_z_m: float, merge_m: float = 0.05,
               dz_m: float = 0.15) -> tuple[sparse.csr_matrix, np.ndarray]:
    """The robot's own walk on one floor as a graph: (csr over places, their (N, 2) positions).

    A place is a pose of ``trajectory_m`` (in order) on the floor, poses within ``merge_m`` of one
    another one place (the robot comes back to a node within a few cm); an edge is a move between
    two consecutive poses on the floor, weighted by its length. Every edge is a straight line the
    robot walked (a blocked move's too, as far as it got)."""
    t = np.asarray(trajectory_m, dtype=np.float64).reshape(-1, 3)
    on = np.flatnonzero(np.abs(t[:, 2] - floor_z_m) <= dz_m)
    if len(on) == 0:
        return sparse.csr_matrix((0, 0)), np.zeros((0, 2))
    xy = t[on, :2]
    pairs = cKDTree(xy).query_pairs(merge_m, output_type="ndarray")
    n = len(xy)
    link = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        sparse.coo_matrix((n, n))
    _, place = connected_components(link, directed=False)
    # Each place sits at its first pose (a node's own position: the robot stood exactly there).
    first = np.full(place.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, place, np.arange(n))
    pos = xy[first]
    consecutive = np.diff(on) == 1  # both poses on the floor, one move apart
    a, b = place[:-1][consecutive], place[1:][consecutive]
    keep = a != b
    m = len(pos)
    # Each move once, whichever way and however often it was walked (a csr sums duplicates).
    key = np.unique(np.minimum(a[keep], b[keep]) * m + np.maximum(a[keep], b[keep]))
    a, b = key // m, key % m
    w = np.maximum(np.linalg.norm(pos[a] - pos[b], axis=1), 1e-6)
    g = sparse.coo_matrix((np.concatenate([w, w]), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(m, m))
    return g.tocsr(), pos


def _cells_of(occ: OccupancyGrid, pos: np.ndarray, tree: cKDTree | None, snap_m: float = 0.5) -> np.ndarray:
    """Graph node of each position: the nearest cell of ``tree`` (cell indices, in node order)
    within ``snap_m``, -1 where none is."""
    out = np.full(len(pos), -1, dtype=np.int64)
    if tree is None or len(pos) == 0:
        return out
    d, k = tree.query(occ.to_index(pos), distance_upper_bound=snap_m / occ.cell_m)
    ok = np.isfinite(d)
    out[ok] = k[ok]
    return out


def _hub_paths(rg, hub_nodes: np.ndarray, hub_cells: np.ndarray, cell_m: float, entry: int = -1):
    """Shortest paths from every hub over the reachable-cell graph: (dist, pred) rows per hub.

    A region's hubs lie close together, so each search stops at a distance limit well beyond the
    hubs' spread instead of sweeping the whole floor. Searches within a limit are exact for every
    node they reach; the rows of a search that missed a hub (or the entry cell) are redone with
    twice the limit, then without one, so the result is the unlimited one.
    """
    spread = float(np.ptp(hub_cells, axis=0).max()) * cell_m if len(hub_cells) > 1 else 0.0
    limit = 1.5 * spread + 3.0
    dist, pred = dijkstra(rg, indices=hub_nodes, return_predecessors=True, limit=limit)
    need = list(hub_nodes) + ([entry] if entry >= 0 else [])
    for attempt in range(3):
        missing = ~np.isfinite(dist[:, need]).all(axis=1)
        if not missing.any():
            break
        limit = limit * 2.0 if attempt < 2 else np.inf
        d2, p2 = dijkstra(rg, indices=hub_nodes[missing], return_predecessors=True, limit=limit)
        dist[missing], pred[missing] = d2, p2
    return dist, pred


def _voxel_downsample(occ, cand_idx, cand_nodes, clear, grid_m):
    """One hub per ``grid_m`` voxel: the candidate cell with the most clearance."""
    vox = np.floor((cand_idx + 0.5) * occ.cell_m / grid_m).astype(np.int64)
    key = vox[:, 0] * 1_000_003 + vox[:, 1]
    c = clear[cand_idx[:, 0], cand_idx[:, 1]]
    order = np.lexsort((-c, key))
    _, first = np.unique(key[order], return_index=True)
    pick = order[first]
    return cand_idx[pick], cand_nodes[pick]
