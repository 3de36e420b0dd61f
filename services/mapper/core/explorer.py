"""Active scene exploration (paper 4.1, Algorithm 1, step 1): frontier DFS over predicted waypoints.

The robot starts anywhere, looks around, asks the waypoint predictor for candidates and adds them
to the grid graph as observed nodes; the newest frontier is visited next (depth first), walking back
along traversed edges when a branch is exhausted. A candidate that the robot cannot reach is marked
unreachable and never tried again. Exploration ends when no frontier is left (the paper's rule).
A safety budget only guards against a predictor that keeps inventing frontiers: it grows with the
area discovered so far (``steps_per_m2``), so a 1,000 m2 building is not cut short where a 100 m2
flat would be; a wall-time budget and a hard cap may be set too. Whatever ends the run is recorded
in ``stop_reason``, with a coverage estimate.

Stairs: the predictor judges one panorama at a time, and near the top (or bottom) of a flight too
few treads remain in view to tell a staircase from a bed. The robot itself knows better: a move
that rose or fell like a flight is followed by a push on in the same direction (``stair_follow_m``),
until the ground levels out. A flight whose continuation could not be walked keeps the exploration
from counting as finished (``open_stairs``).

Every panorama also feeds a 360-ray free-space scan kept for the occupancy map that the tour
planner needs.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol, runtime_checkable

import networkx as nx
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.schemas import Candidate, MoveResult, MoveStatus, Panorama, Pose

from services.mapper.core.errors import ExplorationError
from services.mapper.core.frontier import FreeSpaceMap, FrontierConfig
from services.mapper.core.sidestep import SidestepConfig, move_sidestepping
from services.mapper.core.navgraph import GridGraph, NodeStatus
from services.mapper.core.predictor import (
    GeometricPredictor,
    GeometricPredictorConfig,
    WaypointPredictor,
)

log = logging.getLogger(__name__)


@runtime_checkable
class ExplorerRobot(Protocol):
    """What exploration needs from a robot (robot-io's sim, a real robot, a test fake)."""

    def observe(self) -> Panorama: ...

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult: ...


class ExplorationConfig(BaseModel):
    """Knobs of the frontier DFS. Distances are horizontal unless named otherwise."""

    model_config = ConfigDict(extra="forbid")

    dxy_m: float = Field(0.2, gt=0.0)
    dz_m: float = Field(0.5, gt=0.0)
    # Safety budget, scaled by the area discovered (1 m cells holding any graph node): panoramas
    # may number ``min_steps + steps_per_m2 * area``. A finished exploration needs about one
    # panorama per reachable m2 (bench/mapper.py), so the default leaves twice that.
    min_steps: int = Field(100, ge=1)
    steps_per_m2: float = Field(2.0, gt=0.0)
    moves_per_step: float = Field(12.0, gt=0.0)  # move_to calls (transit included) per budgeted step
    max_steps: int | None = Field(None, ge=1)  # a hard cap on panoramas, whatever the area
    stair_rise_m: float = Field(0.15, gt=0.0)  # a move that rises or falls this much was on stairs
    stair_follow_m: float = Field(1.5, gt=0.0)  # how far on the robot pushes after such a move
    floor_min_nodes: int = Field(5, ge=1)  # visited nodes at one height that make it a floor
    replan_attempts: int = Field(3, ge=1, le=20)  # walks re-planned around blocked traversed edges
    reconnect_radius_m: float = Field(3.0, gt=0.0)  # direct moves that may rejoin a stranded node
    visit_radius_m: float = Field(0.8, gt=0.0)  # a frontier this close to a visited node is covered
    # ... if that node's scan saw it: the ray towards it reached at least this close to it. A node
    # behind a wall (the next room, a stairwell's shaft) covers nothing on the other side.
    sight_margin_m: float = Field(0.15, ge=0.0)
    frontier_merge_m: float = Field(0.5, ge=0.0)  # candidates closer than this to a frontier merge
    same_floor_dz_m: float = Field(0.4, gt=0.0)
    min_progress_m: float = Field(0.3, ge=0.0)  # a blocked move shorter than this adds no node
    scan_angle_bins: int = Field(360, ge=36, le=1440)
    time_budget_s: float | None = Field(None, gt=0.0)
    # The scans' own free-space map: when the predictor's candidates run out, reachable frontiers
    # of the map (free space beside unseen space) become candidates too (see frontier.py).
    frontier: FrontierConfig = Field(default_factory=FrontierConfig)
    # On the way to a frontier only the narrow body reaches, a move that a jamb stops in its first
    # decimetres is tried again a few centimetres aside (sidestep.py): the map places such a
    # passage's middle to within a cell.
    sidestep: SidestepConfig = Field(default_factory=SidestepConfig)


@dataclass(frozen=True)
class Scan:
    """One panorama reduced to what mapping needs: where, and the obstacle range per direction."""

    position_m: np.ndarray  # (3,) floor point
    heading_rad: float
    obstacle_m: np.ndarray  # (scan_angle_bins,), relative angles k * 2pi/n; inf none, nan unseen
    node: str
    # The panorama's robot time and its entry in the trajectory: the pose graph re-places the
    # exploration by them after it ends (replace.py).
    timestamp_s: float = math.nan
    trajectory_index: int = -1


@dataclass(frozen=True)
class ExplorationStep:
    """Where a running exploration stands after one panorama (what its progress events say).

    ``seen`` counts every node the graph holds (visited, frontiers, covered, unreachable);
    ``floors`` the levels of the free-space map; ``time_left_s`` is a rate estimate: the mean wall
    time per panorama so far times the panoramas still expected (open frontiers, capped by the step
    budget). A frontier is often covered on the way to another, so it errs long, never short by
    more than the frontiers the predictor has not proposed yet."""

    step: int
    visited: int
    seen: int
    open_frontiers: int
    floors: int
    coverage_estimate: float | None  # None: not measured at this step (see ``coverage_every_s``)
    elapsed_s: float
    time_left_s: float
    step_budget: int


class StopReason(StrEnum):
    EXHAUSTED = "exhausted"  # no frontier left: the paper's end
    STEPS = "steps"  # the area-scaled panorama budget (or the hard cap) ran out
    MOVES = "moves"
    TIME = "time"


@dataclass
class ExplorationResult:
    graph: GridGraph
    scans: list[Scan]
    trajectory_m: np.ndarray  # (T, 3) poses after every move, in order
    visit_order: list[str]
    steps: int  # panoramas taken
    moves: int  # move_to calls
    unreachable: int
    blocked_moves: int
    # True: no frontier left to try, none of the map's left open, and no flight left unclimbed;
    # False: see stop_reason, open_frontiers and open_stairs. It is the explorer's own map's verdict: where
    # depth noise hides the way on, nothing is left open on that map either. generated:2013:floors=2's
    # stairs lie past a passage the noise-free robot crossed in 0.1-0.2 m steps; the noisy robot
    # (bench.mapper --noise noisy, 128 px) never found them on noise seeds 0-2 and ended finished at
    # 48.6-48.8 % of the reachable area (99.9 % noise-free). The depth's sigma alone (0.01 m * depth^2,
    # exact poses, no holes) loses them on the same seeds; holes alone (5 %) do not.
    finished: bool
    duration_s: float
    start_pose: Pose
    scan_angles_rad: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stop_reason: StopReason = StopReason.EXHAUSTED
    discovered_m2: float = 0.0  # 1 m cells holding a graph node (what the budget scaled with)
    coverage_estimate: float = 1.0  # share of the mapped reachable free area within reach of a visited node
    mapped_free_m2: float = 0.0  # that free area (the explorer's own map)
    map_frontiers: int = 0  # candidates the map's frontiers added (the predictor did not propose them)
    narrow_frontiers: int = 0  # ... of them behind passages only the narrow body passes
    # Frontiers of the map that no visited node came near and that were never tried, left when the
    # exploration ended (seen through a gap the map knows no way through). Those tried and failed
    # count in ``unreachable``. The coverage estimate counts the space behind both as missed.
    open_frontiers: int = 0
    open_stairs: int = 0  # flights seen climbing or descending whose continuation failed
    step_budget: int = 0
    # The largest depth noise the robot's panoramas declared (``Panorama.depth_noise_rel``; 0: exact
    # or not known): the tours look from nearer where it is not 0 (TourConfig.max_depth_sigma_m).
    depth_noise_rel: float = 0.0

    def summary(self) -> dict:
        """What events and map metadata say about how the exploration ended."""
        return {"finished": self.finished, "stop_reason": str(self.stop_reason), "steps": self.steps,
                "step_budget": self.step_budget, "moves": self.moves,
                "discovered_m2": round(self.discovered_m2, 1),
                "coverage_estimate": round(self.coverage_estimate, 3), "mapped_free_m2": round(self.mapped_free_m2, 1),
                "map_frontiers": self.map_frontiers, "narrow_frontiers": self.narrow_frontiers,
                "open_frontiers": self.open_frontiers, "open_stairs": self.open_stairs,
                "depth_noise_rel": self.depth_noise_rel}


class Explorer:
    """Frontier DFS driver. One instance can run several explorations (not concurrently)."""

    def __init__(
        self,
        predictor: WaypointPredictor | None = None,
        config: ExplorationConfig | None = None,
        scanner_config: GeometricPredictorConfig | None = None,
    ):
        self.config = config or ExplorationConfig()
        self.predictor = predictor or GeometricPredictor()
        if scanner_config is None and isinstance(self.predictor, GeometricPredictor):
            # One column walk per panorama serves both the candidates and the scan.
            self.scanner = self.predictor.with_angle_bins(self.config.scan_angle_bins)
        else:
            base = scanner_config or getattr(self.predictor, "config", None) or GeometricPredictorConfig()
            self.scanner = GeometricPredictor(
                base.model_copy(update={"angle_bins": self.config.scan_angle_bins})
            )

    def explore(self, robot: ExplorerRobot, checkpoint: Callable[[], None] | None = None,
                on_step: Callable[[ExplorationStep], None] | None = None,
                coverage_every_s: float = 2.0) -> ExplorationResult:
        """Run the frontier DFS to its end; ``checkpoint`` (if given) is called before every step and
        may raise to abandon the exploration (a cancelled job), which then propagates. ``on_step``
        (if given) hears where the exploration stands after every panorama; the coverage estimate
        in it is refreshed at most every ``coverage_every_s`` of wall time, since it rebuilds the
        reachable free area of every floor (about as long as a panorama's own mapping on a big house)."""
        cfg = self.config
        t0 = time.perf_counter()
        run = _Run(self, robot)
        pano = robot.observe()
        start_pose = pano.pose
        run.arrive(pano, previous=None, travelled_m=0.0)
        reason = StopReason.EXHAUSTED
        coverage_at = -math.inf
        while True:
            if on_step is not None:
                now = time.perf_counter()
                coverage = None
                if now - coverage_at >= coverage_every_s:
                    coverage, coverage_at = run.coverage_estimate()[0], now
                on_step(run.progress(now - t0, coverage))
            if checkpoint is not None:
                checkpoint()
            budget = run.step_budget()
            if run.steps >= budget:
                reason = StopReason.STEPS
            elif run.moves >= budget * cfg.moves_per_step:
                reason = StopReason.MOVES
            elif cfg.time_budget_s is not None and time.perf_counter() - t0 > cfg.time_budget_s:
                reason = StopReason.TIME
            else:
                target = run.next_frontier()
                if target is None:
                    break
                run.visit(target)
                continue
            log.warning("exploration stopped by its %s budget: %d steps, %d moves, %.0f m2 discovered",
                        reason, run.steps, run.moves, run.discovered_m2())
            break
        g = run.graph
        open_stairs = run.open_stairs()
        coverage, free_m2, left_open = run.coverage_estimate()
        return ExplorationResult(
            graph=g,
            scans=run.scans,
            trajectory_m=np.array(run.trajectory),
            visit_order=run.visit_order,
            steps=run.steps,
            moves=run.moves,
            unreachable=len(g.nodes_with(NodeStatus.UNREACHABLE)),
            blocked_moves=run.blocked,
            finished=reason == StopReason.EXHAUSTED and open_stairs == 0 and left_open == 0,
            duration_s=time.perf_counter() - t0,
            start_pose=start_pose,
            scan_angles_rad=self.scanner.angles_rad.copy(),
            stop_reason=reason,
            discovered_m2=run.discovered_m2(),
            coverage_estimate=coverage,
            mapped_free_m2=free_m2,
            map_frontiers=run.map_frontiers,
            narrow_frontiers=run.narrow_frontiers,
            open_frontiers=left_open,
            open_stairs=open_stairs,
            step_budget=run.step_budget(),
            depth_noise_rel=run.depth_noise_rel,
        )


class _Run:
    """State of one exploration."""

    def __init__(self, explorer: Explorer, robot: ExplorerRobot):
        self.ex = explorer
        self.cfg = explorer.config
        self.robot = robot
        self.graph = GridGraph(self.cfg.dxy_m, self.cfg.dz_m)
        self.frontiers: list[str] = []  # DFS stack
        self.scans: list[Scan] = []
        self.trajectory: list[np.ndarray] = []
        self.visit_order: list[str] = []
        self.here: str | None = None
        self.pose: Pose | None = None
        self.steps = 0
        self.moves = 0
        self.blocked = 0
        self.cells: set[tuple[int, int, int]] = set()  # 1 m cells holding a node: the discovered area
        self.stair_nodes: set[str] = set()  # visited nodes reached by a move that climbed or fell
        self.node_scan: dict[str, Scan] = {}  # the latest panorama's scan taken at each visited node
        self.space = FreeSpaceMap(explorer.scanner.angles_rad, self.cfg.frontier, self.cfg.same_floor_dz_m)
        self.map_frontiers = 0
        self.narrow_frontiers = 0
        self.map_targets: list[str] = []  # the nodes the map's frontiers added
        self.depth_noise_rel = 0.0
        # On the way to a frontier behind a passage only the narrow body passes: its moves may take
        # a sidestep and the edges laid on it are marked narrow (navgraph.connect).
        self.narrow_way = False

    # --- budget and bookkeeping -------------------------------------------------------------------

    def _cell(self, pos: np.ndarray) -> tuple[int, int, int]:
        return (math.floor(pos[0]), math.floor(pos[1]), math.floor(pos[2] / (2.0 * self.cfg.same_floor_dz_m)))

    def discovered_m2(self) -> float:
        return float(len(self.cells))

    def step_budget(self) -> int:
        budget = int(self.cfg.min_steps + self.cfg.steps_per_m2 * len(self.cells))
        return min(budget, self.cfg.max_steps) if self.cfg.max_steps is not None else budget

    def progress(self, elapsed_s: float, coverage: float | None) -> ExplorationStep:
        g = self.graph
        open_frontiers = len(g.nodes_with(NodeStatus.FRONTIER))
        budget = self.step_budget()
        expected = min(open_frontiers, max(0, budget - self.steps))
        return ExplorationStep(
            step=self.steps, visited=len(g.nodes_with(NodeStatus.VISITED)), seen=len(g.g),
            open_frontiers=open_frontiers, floors=len(self.space.levels), coverage_estimate=coverage,
            elapsed_s=elapsed_s, time_left_s=elapsed_s / max(1, self.steps) * expected, step_budget=budget)

    def _floor_nodes(self) -> dict[float, list[tuple[str, np.ndarray]]]:
        """Visited nodes off the stairs, by floor level of the free-space map."""
        out: dict[float, list[tuple[str, np.ndarray]]] = {}
        for n in self.graph.nodes_with(NodeStatus.VISITED):
            if n in self.stair_nodes:
                continue
            p = self.graph.pos(n)
            lv = self.space.level_of(float(p[2]))
            if lv is not None:
                out.setdefault(lv.z_m, []).append((n, p))
        return out

    def coverage_estimate(self) -> tuple[float, float, int]:
        """(Share of the mapped free area reachable from the visited nodes that lies within the
        coverage radius of one, that area m2, frontiers left open and never tried). Free space seen
        through a door but never walked to lowers it; a graph of nodes alone cannot see that space."""
        by_level = {z: np.stack([p[:2] for _, p in nodes]) for z, nodes in self._floor_nodes().items()}
        # Stair nodes stand over the flights, which each floor's map holds as free ground.
        stairs = [n for n in self.stair_nodes if n in self.graph.g]
        # A frontier target stands within max_backoff_m of its frontier, and the next is refused
        # near one that failed (visit_radius_m): a frontier with a failed target that near was
        # tried. (A predictor candidate that failed near it is no attempt at it: a straight move
        # into a gap the map holds a way through only for a narrower body.)
        failed = self.graph.positions([n for n in self.map_targets
                                       if self.graph.status(n) == NodeStatus.UNREACHABLE])
        return self.space.coverage_report(by_level, self.graph.positions(stairs)[:, :2], failed,
                                          self.cfg.frontier.max_backoff_m + self.cfg.visit_radius_m)

    def open_stairs(self) -> int:
        """Stair nodes above the highest explored floor or below the lowest: a flight that leads on.

        A floor here is a height where at least ``floor_min_nodes`` visited nodes pile up (the
        stair nodes themselves left out); a flight between two explored floors is closed.
        """
        g = self.graph
        stairs = [n for n in self.stair_nodes if n in g.g]
        z = g.positions([n for n in g.nodes_with(NodeStatus.VISITED) if n not in self.stair_nodes])[:, 2]
        if not stairs or len(z) == 0:
            return 0
        zs = np.sort(z)
        groups = np.split(zs, np.nonzero(np.diff(zs) > self.cfg.same_floor_dz_m)[0] + 1)
        levels = [float(np.median(grp)) for grp in groups if len(grp) >= self.cfg.floor_min_nodes]
        if not levels:
            return 0
        sz = g.positions(stairs)[:, 2]
        rise = self.cfg.stair_rise_m
        return int(np.sum((sz > max(levels) + rise) | (sz < min(levels) - rise)))

    # --- graph updates --------------------------------------------------------------------------

    def arrive(self, pano: Panorama, previous: str | None, travelled_m: float) -> str:
        """Take the panorama at the robot's pose: a visited node, new candidates, a scan."""
        self.steps += 1
        self.pose = pano.pose
        self.depth_noise_rel = max(self.depth_noise_rel, float(pano.depth_noise_rel))
        pos = pano.pose.xyz
        at = len(self.trajectory)
        self.trajectory.append(pos.copy())
        nid = self.graph.add_visited(pos, order=self.steps)
        self.cells.add(self._cell(pos))
        self.visit_order.append(nid)
        if previous is not None:
            self.graph.connect(previous, nid, max(travelled_m, 1e-3), narrow=self.narrow_way)
        self.here = nid
        obstacle = self.ex.scanner.obstacle_distance(pano)
        scan = Scan(pos.copy(), pano.pose.heading_rad, obstacle, nid, float(pano.timestamp_s), at)
        self.scans.append(scan)
        self.node_scan[nid] = scan
        if previous is None or abs(pos[2] - self.graph.pos(previous)[2]) < self.cfg.stair_rise_m:
            # On a flight the 2-D map of no floor holds what the panorama sees (regions.py too).
            self.space.add_scan(pos, pano.pose.heading_rad, obstacle)
        self._cover_near(nid, pos)
        cands = self.ex.predictor.predict(pano)
        # Push the best candidate last so that the DFS takes it first.
        for cand in sorted(cands, key=lambda c: c.score):
            self._add_candidate(nid, pos, cand)
        if previous is not None:
            self._follow_stairs(nid, self.graph.pos(previous), pos)
        return nid

    def _follow_stairs(self, nid: str, came_from: np.ndarray, pos: np.ndarray) -> None:
        """After a move that climbed or descended like a flight, push on the same way, first."""
        d = pos - came_from
        run = math.hypot(d[0], d[1])
        if abs(d[2]) < self.cfg.stair_rise_m or run < 1e-3:
            return
        self.stair_nodes.add(nid)
        target = pos + np.array([d[0], d[1], 0.0]) / run * self.cfg.stair_follow_m
        if self._seen_near(target):
            return  # that part of the flight was walked already
        f = self.graph.add_observed(target, nid, 1.0)
        if f is not None:
            self.cells.add(self._cell(target))
            self.frontiers.append(f)

    def _add_candidate(self, parent: str, pos: np.ndarray, cand: Candidate) -> None:
        target = pos + np.array([cand.dx_m, cand.dy_m, 0.0])
        if self._seen_near(target):
            return
        if self._near(target, (NodeStatus.FRONTIER,), self.cfg.frontier_merge_m):
            return
        if self._near(target, (NodeStatus.UNREACHABLE,), self.cfg.frontier_merge_m):
            return  # a place we already failed to reach stays failed
        nid = self.graph.add_observed(target, parent, cand.score)
        if nid is not None:
            self.cells.add(self._cell(target))
            self.frontiers.append(nid)

    def _near(self, target: np.ndarray, status: tuple[NodeStatus, ...], radius: float) -> bool:
        return bool(self.graph.near(target, radius, self.cfg.same_floor_dz_m, *status))

    def _sees(self, nid: str, target: np.ndarray) -> bool:
        """Did the scan taken at visited node ``nid`` see ``target`` (no obstacle on the way)?

        A node without a scan (none in this run) is trusted as before: nearness alone.
        """
        scan = self.node_scan.get(nid)
        if scan is None:
            return True
        d = target[:2] - scan.position_m[:2]
        dist = math.hypot(d[0], d[1])
        if dist <= self.cfg.sight_margin_m:
            return True
        n = len(scan.obstacle_m)
        k = int(round((math.atan2(d[1], d[0]) - scan.heading_rad) / (2.0 * math.pi / n))) % n
        reach = scan.obstacle_m[k]
        return bool(not np.isnan(reach) and reach >= dist - self.cfg.sight_margin_m)

    def _seen_near(self, target: np.ndarray) -> bool:
        """Is ``target`` close to a visited node that saw it? Then going there adds nothing."""
        return any(self._sees(v, target) for v in self.graph.near(
            target, self.cfg.visit_radius_m, self.cfg.same_floor_dz_m, NodeStatus.VISITED))

    def _cover_near(self, nid: str, pos: np.ndarray) -> None:
        """Frontiers that a new visited node sees from close by are covered, not visited."""
        for f in self.graph.near(pos, self.cfg.visit_radius_m, self.cfg.same_floor_dz_m, NodeStatus.FRONTIER):
            if self._sees(nid, self.graph.pos(f)):
                self.graph.set_status(f, NodeStatus.COVERED)

    # --- DFS --------------------------------------------------------------------------------------

    def next_frontier(self) -> str | None:
        for _ in range(2):
            while self.frontiers:
                f = self.frontiers.pop()
                if f in self.graph.g and self.graph.status(f) == NodeStatus.FRONTIER:
                    return f
            if not self.cfg.frontier.enabled or not self._add_map_frontiers():
                return None
        return None

    def _add_map_frontiers(self) -> int:
        """The predictor has nothing left: push the free-space map's reachable frontiers, nearest
        last (taken first). Those already seen from close by, or near a place that failed, are not
        new. When none is left for the robot's body, the frontiers behind passages only a narrower
        body passes are tried (``narrow_body_radius_m``): generated:2:area=500:floors=3 hid its
        hallway, dining room and every flight behind a 0.35 m gap between a bed and a nightstand,
        and the exploration ended 'finished' at 26 % coverage. None left means the exploration is
        over."""
        found = self._map_targets(None)
        if not found and self.cfg.frontier.narrow_body_radius_m < self.cfg.frontier.body_radius_m:
            found = self._map_targets(self.cfg.frontier.narrow_body_radius_m)
            self.narrow_frontiers += len(found)
        here = self.pose.xyz
        found = [(float(np.linalg.norm(self.graph.pos(n) - here)), n) for n in found]
        for _, nid in sorted(found, reverse=True):
            self.cells.add(self._cell(self.graph.pos(nid)))
            self.frontiers.append(nid)
        self.map_frontiers += len(found)
        if found:
            log.debug("%d frontiers of the free-space map added", len(found))
        return len(found)

    def _map_targets(self, body_radius_m: float | None) -> list[str]:
        """The map's frontier targets for a body of ``body_radius_m`` (the config's: None) as new
        frontier nodes; a target out of straight sight keeps the corners of its way."""
        out: list[str] = []
        stairs = self.graph.positions([n for n in self.stair_nodes if n in self.graph.g])[:, :2]
        for z, nodes in self._floor_nodes().items():
            if len(nodes) < self.cfg.floor_min_nodes:
                continue
            for t in self.space.frontier_targets(z, nodes, self.cfg.visit_radius_m, stairs, accept=self._new_target,
                                                 body_radius_m=body_radius_m):
                nid = self.graph.add_observed(t.position_m, t.parent, 0.5)
                if nid is not None:
                    if body_radius_m is not None:
                        self.graph.g.nodes[nid]["narrow"] = True  # its way may need a sidestep
                    if t.way_m:
                        self.graph.g.nodes[nid]["way"] = [np.array([w[0], w[1], z]) for w in t.way_m]
                    out.append(nid)
                    self.map_targets.append(nid)
        return out

    def _new_target(self, p: np.ndarray) -> bool:
        """A map frontier's target is new unless seen from close by, already a frontier, or near a
        place that failed."""
        return not (self._seen_near(p) or self._near(p, (NodeStatus.FRONTIER,), self.cfg.frontier_merge_m)
                    or self._near(p, (NodeStatus.UNREACHABLE,), self.cfg.visit_radius_m))

    def visit(self, target: str) -> None:
        g = self.graph
        parent = g.g.nodes[target]["parent"]
        if parent != self.here and not self._walk_to(parent):
            # Could not get back to where the frontier was seen from: give it up.
            log.info("frontier %s given up: its parent %s is out of reach from %s", target, parent, self.here)
            g.set_status(target, NodeStatus.UNREACHABLE)
            return
        self.narrow_way = bool(g.g.nodes[target].get("narrow", False))
        try:
            self._approach(target)
        finally:
            self.narrow_way = False

    def _approach(self, target: str) -> None:
        """From the frontier's parent, along its way if it has one, to the frontier."""
        g = self.graph
        walked = 0.0  # on the way's legs since the last node
        way = g.g.nodes[target].get("way") or []
        if way:
            ok, walked = self._walk_legs(way)
            if not ok:
                # Blocked on the way (a panorama where it stopped, if it got anywhere new).
                self.blocked += 1
                g.set_status(target, NodeStatus.UNREACHABLE)
                return
            if g.status(target) != NodeStatus.FRONTIER:
                # A panorama on the way saw it from close by; a few cm past the last node are
                # walked back so the graph stays truthful.
                self._return_to(self.here)
                return
        base = self.here
        goal = g.pos(target)
        start = self.pose.xyz
        res = self._move(goal[0] - start[0], goal[1] - start[1], sidestep=self.narrow_way)
        end = res.pose.xyz
        travelled = walked + res.travelled_m
        if res.status == MoveStatus.REACHED:
            # The robot stands at the candidate; on stairs its true height puts it in another
            # voxel. The observed voxel stays in the graph, resolved, so that the same candidate
            # seen again from elsewhere is recognised and not chased in a loop.
            if g.node_id(end) != target:
                g.set_status(target, NodeStatus.COVERED)
            self.arrive(self.robot.observe(), previous=base, travelled_m=travelled)
            return
        self.blocked += 1
        g.set_status(target, NodeStatus.UNREACHABLE)
        log.debug("candidate %s unreachable (blocked after %.2f m)", target, travelled)
        if travelled >= self.cfg.min_progress_m and not self._near(
            end, (NodeStatus.VISITED,), self.cfg.visit_radius_m * 0.5
        ):
            self.arrive(self.robot.observe(), previous=base, travelled_m=travelled)
        elif travelled > 1e-3:
            # Stranded between nodes: go back to the node so the graph stays truthful.
            self.here = base
            self._return_to(base)

    def _walk_legs(self, corners: list[np.ndarray]) -> tuple[bool, float]:
        """Walk straight legs from the current node through ``corners`` (the map's way around
        furniture, through a narrow passage), a panorama wherever a leg ends at least
        ``min_progress_m`` past the last node, so every graph edge stays a straight move.
        (False, 0) when a leg is blocked: a panorama where the robot stopped if it got that far,
        else back to the last node; else (True, metres walked past the last node)."""
        walked = 0.0  # since the last node
        for wp in corners:
            cur = self.pose.xyz
            res = self._move(wp[0] - cur[0], wp[1] - cur[1], sidestep=self.narrow_way)
            walked += res.travelled_m
            if res.status == MoveStatus.REACHED and walked < self.cfg.min_progress_m:
                continue
            if walked >= self.cfg.min_progress_m and not (
                    res.status != MoveStatus.REACHED
                    and self._near(res.pose.xyz, (NodeStatus.VISITED,), self.cfg.visit_radius_m * 0.5)):
                self.arrive(self.robot.observe(), previous=self.here, travelled_m=walked)
                walked = 0.0
            if res.status != MoveStatus.REACHED:
                if walked > 1e-3:
                    self._return_to(self.here)
                return False, 0.0
        return True, walked

    def _walk_to(self, goal: str) -> bool:
        """Follow traversed edges from the current node to ``goal``, re-planning around a blocked one.

        An edge walked one way may not be walkable back the same straight way (the simulator slides
        along a door jamb; a real robot's odometry drifts). A blocked edge is dropped and the robot
        steps back to its node; when that leaves the node with no way on, it reconnects it to a
        visited neighbour by a direct move, so one bad edge never strands the whole exploration.
        """
        g = self.graph
        for _ in range(self.cfg.replan_attempts):
            try:
                path = nx.shortest_path(g.walked(), self.here, goal, weight="length")
            except (nx.NetworkXNoPath, nx.NodeNotFound):
                if not self._reconnect():
                    return False
                continue
            if self._follow(path):
                return True
        return False

    def _follow(self, path: list[str]) -> bool:
        g = self.graph
        for nxt in path[1:]:
            p = g.pos(nxt)
            cur = self.pose.xyz
            res = self._move(p[0] - cur[0], p[1] - cur[1], sidestep=g.narrow(self.here, nxt))
            if res.status != MoveStatus.REACHED:
                self.blocked += 1
                log.info("blocked on a traversed edge %s -> %s after %.2f m", self.here, nxt, res.travelled_m)
                g.remove_edge(self.here, nxt)
                self._return_to(self.here)
                return False
            self.here = nxt
        return True

    def _return_to(self, nid: str) -> None:
        """Step back to node ``nid`` (the current node) after a blocked or abandoned move. Where
        the robot does not get back (it slid off a flight's side and stands a floor lower), the
        graph's idea of where it stands is wrong: it takes a panorama where it is, a new node
        that the next walk rejoins by :meth:`_reconnect`. generated:4:area=200:floors=2 believed
        its robot on a stair node 0.56 m up while it stood on the ground floor 0.7 m away, gave
        up every frontier left as out of reach, and ended at 51 % coverage, one floor."""
        back = self.graph.pos(nid)[:2] - self.pose.xyz[:2]
        if math.hypot(*back) > 1e-3:
            self._move(*back)
        d = self.pose.xyz - self.graph.pos(nid)
        if math.hypot(d[0], d[1]) > self.cfg.min_progress_m or abs(d[2]) >= self.cfg.stair_rise_m:
            log.info("robot did not get back to %s (%.2f m off, %.2f m below or above): a new node where it is",
                     nid, math.hypot(d[0], d[1]), d[2])
            self.arrive(self.robot.observe(), previous=None, travelled_m=0.0)

    def _reconnect(self) -> bool:
        """Join the current node to the nearest visited nodes it has no traversed path to, directly."""
        g = self.graph
        here = g.pos(self.here)
        reach = nx.node_connected_component(g.walked(), self.here)
        others = [n for n in g.nodes_with(NodeStatus.VISITED) if n not in reach]
        if not others:
            return False
        p = g.positions(others)
        same = np.abs(p[:, 2] - here[2]) < self.cfg.same_floor_dz_m
        dist = np.linalg.norm(p[:, :2] - here[:2], axis=1)
        for k in np.argsort(np.where(same, dist, np.inf))[: self.cfg.replan_attempts]:
            if not same[k] or dist[k] > self.cfg.reconnect_radius_m:
                break
            res = self._move(*(p[k, :2] - self.pose.xyz[:2]))
            if res.status == MoveStatus.REACHED:
                g.connect(self.here, others[k], res.travelled_m)
                self.here = others[k]
                return True
            self.blocked += 1
            self._return_to(self.here)
        return self._reconnect_by_map([o for o, s in zip(others, same) if s]) or self._bridge()

    def _bridge(self) -> bool:
        """Rejoin the rest where the two parts of the graph touch, not where the robot stands: walk
        to the node of its own part nearest a node of another part at the same height, and move
        across. A robot that slid off a flight and climbed on from where it landed explores the upper
        floor as a part whose only contact with the rest is on the stairs; :meth:`_reconnect` looks
        only near the robot, a floor away from every node of the rest. generated:1011:floors=2
        (noisy) so gave up 21 frontiers of its ground floor, two stair nodes of the two parts 0.2 m
        apart, and its tours could not reach three of its six ground-floor regions."""
        g = self.graph
        reach = nx.node_connected_component(g.walked(), self.here)
        visited = g.nodes_with(NodeStatus.VISITED)
        mine, others = [n for n in visited if n in reach], [n for n in visited if n not in reach]
        if not others:
            return False
        pa, pb = g.positions(mine), g.positions(others)
        level = np.abs(pa[:, None, 2] - pb[None, :, 2]) < self.cfg.same_floor_dz_m
        gap = np.where(level, np.linalg.norm(pa[:, None, :2] - pb[None, :, :2], axis=2), np.inf)
        for k in np.argsort(gap, axis=None)[: self.cfg.replan_attempts]:
            i, j = np.unravel_index(k, gap.shape)
            if gap[i, j] > self.cfg.reconnect_radius_m:
                break
            try:
                way = nx.shortest_path(g.walked(), self.here, mine[i], weight="length")
            except (nx.NetworkXNoPath, nx.NodeNotFound):
                return False
            if not self._follow(way):
                return False  # an edge of the way was dropped: the caller plans again
            res = self._move(*(pb[j, :2] - self.pose.xyz[:2]))
            if res.status == MoveStatus.REACHED:
                g.connect(self.here, others[j], res.travelled_m)
                self.here = others[j]
                log.info("rejoined the rest of the graph across %s -> %s (%.2f m)", mine[i], others[j], gap[i, j])
                return True
            self.blocked += 1
            self._return_to(self.here)
            if self.here not in reach:
                # It did not get back (a slide off the flight): a new node of its own, which the
                # caller's next plan rejoins; the generated:3:floors=2 ladder (noise seed 1) raised
                # NetworkXNoPath here, planning the next crossing from that unjoined node.
                return False
        return False

    def _reconnect_by_map(self, others: list[str]) -> bool:
        """No straight move rejoins the rest: walk the free-space map's shortest way to the nearest
        node of the rest (the door the robot came in by, when the edge through it cannot be walked
        back), a panorama at every corner so each edge stays a straight move. Without it, a robot
        stranded in a corner room gave up every frontier left (generated:1:area=1000: 55 %)."""
        if not others or not self.cfg.frontier.enabled:
            return False
        g = self.graph
        here = self.pose.xyz
        lv = self.space.level_of(float(here[2]))
        if lv is None:
            return False
        goals = g.positions(others)[:, :2]
        way = self.space.path(lv.z_m, here[:2], goals)
        if way is None:  # the way back may be a passage only the narrow body passes
            way = self.space.path(lv.z_m, here[:2], goals, body_radius_m=self.cfg.frontier.narrow_body_radius_m)
        if way is None:
            return False
        goal, waypoints = way
        log.info("stranded at %s: rejoining %s by the map's way (%d legs)", self.here, others[goal], len(waypoints))
        walked = 0.0  # since the last node
        for k, wp in enumerate(waypoints):
            cur = self.pose.xyz
            res = self._move(wp[0] - cur[0], wp[1] - cur[1])
            walked += res.travelled_m
            if res.status == MoveStatus.REACHED and k == len(waypoints) - 1:
                g.connect(self.here, others[goal], walked)
                self.here = others[goal]
                return True
            if res.status != MoveStatus.REACHED:
                self.blocked += 1
                if walked < self.cfg.min_progress_m:
                    self._return_to(self.here)
                    return False
            # A corner of the way (or as far as a blocked leg got) a short leg past the last node
            # or more: a node, so the graph's edges stay straight moves (a few cm of a corner cut
            # around a jamb are left to the robot's sliding).
            if walked >= self.cfg.min_progress_m or res.status != MoveStatus.REACHED:
                self.arrive(self.robot.observe(), previous=self.here, travelled_m=walked)
                walked = 0.0
            if res.status != MoveStatus.REACHED:
                return False
        return False

    def _move(self, dx: float, dy: float, sidestep: bool = False) -> MoveResult:
        """One straight move; ``sidestep``: through a passage the map holds as narrow, tried again
        aside where blocked early (sidestep.py)."""
        self.moves += 1
        d = math.hypot(dx, dy)
        if d > 19.0:
            raise ExplorationError(f"refusing a {d:.1f} m single move; graph edges are short")
        if sidestep:
            res = move_sidestepping(self.robot, float(dx), float(dy), self.cfg.sidestep)
        else:
            res = self.robot.move_to(float(dx), float(dy))
        self.pose = res.pose
        self.trajectory.append(res.pose.xyz.copy())
        return res
