"""Active scene exploration (paper 4.1, Algorithm 1, step 1): frontier DFS over predicted waypoints.

The robot starts anywhere, looks around, asks the waypoint predictor for candidates and adds them
to the grid graph as observed nodes; the newest frontier is visited next (depth first), walking back
along traversed edges when a branch is exhausted. A candidate that the robot cannot reach is marked
unreachable and never tried again; exploration ends when no frontier is left or the step budget is
spent. Every panorama also feeds a 360-ray free-space scan kept for the occupancy map that the tour
planner needs.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import networkx as nx
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.schemas import Candidate, MoveResult, MoveStatus, Panorama, Pose

from services.mapper.core.errors import ExplorationError
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
    max_steps: int = Field(300, ge=1)  # panoramas taken (waypoints visited)
    max_moves: int = Field(3000, ge=1)  # move_to calls, transit included
    visit_radius_m: float = Field(0.8, gt=0.0)  # a frontier this close to a visited node is covered
    frontier_merge_m: float = Field(0.5, ge=0.0)  # candidates closer than this to a frontier merge
    same_floor_dz_m: float = Field(0.4, gt=0.0)
    min_progress_m: float = Field(0.3, ge=0.0)  # a blocked move shorter than this adds no node
    scan_angle_bins: int = Field(360, ge=36, le=1440)
    time_budget_s: float | None = Field(None, gt=0.0)


@dataclass(frozen=True)
class Scan:
    """One panorama reduced to what mapping needs: where, and the obstacle range per direction."""

    position_m: np.ndarray  # (3,) floor point
    heading_rad: float
    obstacle_m: np.ndarray  # (scan_angle_bins,), relative angles k * 2pi/n; inf none, nan unseen
    node: str


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
    finished: bool  # True: no frontier left; False: a budget ran out
    duration_s: float
    start_pose: Pose
    scan_angles_rad: np.ndarray = field(default_factory=lambda: np.zeros(0))


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
        base = scanner_config or getattr(self.predictor, "config", None) or GeometricPredictorConfig()
        self.scanner = GeometricPredictor(
            base.model_copy(update={"angle_bins": self.config.scan_angle_bins})
        )

    def explore(self, robot: ExplorerRobot) -> ExplorationResult:
        cfg = self.config
        t0 = time.perf_counter()
        run = _Run(self, robot)
        pano = robot.observe()
        start_pose = pano.pose
        run.arrive(pano, previous=None, travelled_m=0.0)
        finished = False
        while True:
            if run.steps >= cfg.max_steps or run.moves >= cfg.max_moves:
                log.info("exploration budget spent: %d steps, %d moves", run.steps, run.moves)
                break
            if cfg.time_budget_s is not None and time.perf_counter() - t0 > cfg.time_budget_s:
                log.info("exploration time budget spent")
                break
            target = run.next_frontier()
            if target is None:
                finished = True
                break
            run.visit(target)
        g = run.graph
        return ExplorationResult(
            graph=g,
            scans=run.scans,
            trajectory_m=np.array(run.trajectory),
            visit_order=run.visit_order,
            steps=run.steps,
            moves=run.moves,
            unreachable=len(g.nodes_with(NodeStatus.UNREACHABLE)),
            blocked_moves=run.blocked,
            finished=finished,
            duration_s=time.perf_counter() - t0,
            start_pose=start_pose,
            scan_angles_rad=self.scanner.angles_rad.copy(),
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

    # --- graph updates --------------------------------------------------------------------------

    def arrive(self, pano: Panorama, previous: str | None, travelled_m: float) -> str:
        """Take the panorama at the robot's pose: a visited node, new candidates, a scan."""
        self.steps += 1
        self.pose = pano.pose
        pos = pano.pose.xyz
        self.trajectory.append(pos.copy())
        nid = self.graph.add_visited(pos, order=self.steps)
        self.visit_order.append(nid)
        if previous is not None:
            self.graph.connect(previous, nid, max(travelled_m, 1e-3))
        self.here = nid
        obstacle = self.ex.scanner.obstacle_distance(pano)
        self.scans.append(Scan(pos.copy(), pano.pose.heading_rad, obstacle, nid))
        self._cover_near(pos)
        cands = self.ex.predictor.predict(pano)
        # Push the best candidate last so that the DFS takes it first.
        for cand in sorted(cands, key=lambda c: c.score):
            self._add_candidate(nid, pos, cand)
        return nid

    def _add_candidate(self, parent: str, pos: np.ndarray, cand: Candidate) -> None:
        target = pos + np.array([cand.dx_m, cand.dy_m, 0.0])
        if self._near(target, (NodeStatus.VISITED,), self.cfg.visit_radius_m):
            return
        if self._near(target, (NodeStatus.FRONTIER,), self.cfg.frontier_merge_m):
            return
        if self._near(target, (NodeStatus.UNREACHABLE,), self.cfg.frontier_merge_m):
            return  # a place we already failed to reach stays failed
        nid = self.graph.add_observed(target, parent, cand.score)
        if nid is not None:
            self.frontiers.append(nid)

    def _near(self, target: np.ndarray, status: tuple[NodeStatus, ...], radius: float) -> bool:
        nodes = self.graph.nodes_with(*status)
        if not nodes or radius <= 0:
            return False
        p = self.graph.positions(nodes)
        dxy = np.linalg.norm(p[:, :2] - target[:2], axis=1)
        dz = np.abs(p[:, 2] - target[2])
        return bool(np.any((dxy < radius) & (dz < self.cfg.same_floor_dz_m)))

    def _cover_near(self, pos: np.ndarray) -> None:
        """Frontiers that a new visited node makes redundant are covered, not visited."""
        r = self.cfg.visit_radius_m
        for f in self.graph.nodes_with(NodeStatus.FRONTIER):
            p = self.graph.pos(f)
            if np.linalg.norm(p[:2] - pos[:2]) < r and abs(p[2] - pos[2]) < self.cfg.same_floor_dz_m:
                self.graph.g.nodes[f]["status"] = NodeStatus.COVERED

    # --- DFS --------------------------------------------------------------------------------------

    def next_frontier(self) -> str | None:
        while self.frontiers:
            f = self.frontiers.pop()
            if f in self.graph.g and self.graph.status(f) == NodeStatus.FRONTIER:
                return f
        return None

    def visit(self, target: str) -> None:
        g = self.graph
        parent = g.g.nodes[target]["parent"]
        if parent != self.here and not self._walk_to(parent):
            # Could not get back to where the frontier was seen from: give it up.
            g.g.nodes[target]["status"] = NodeStatus.UNREACHABLE
            return
        goal = g.pos(target)
        start = self.pose.xyz
        res = self._move(goal[0] - start[0], goal[1] - start[1])
        end = res.pose.xyz
        travelled = res.travelled_m
        if res.status == MoveStatus.REACHED:
            # The robot stands at the candidate; on stairs its true height puts it in another
            # voxel. The observed voxel stays in the graph, resolved, so that the same candidate
            # seen again from elsewhere is recognised and not chased in a loop.
            if g.node_id(end) != target:
                g.g.nodes[target]["status"] = NodeStatus.COVERED
            self.arrive(self.robot.observe(), previous=parent, travelled_m=travelled)
            return
        self.blocked += 1
        g.g.nodes[target]["status"] = NodeStatus.UNREACHABLE
        log.debug("candidate %s unreachable (blocked after %.2f m)", target, travelled)
        if travelled >= self.cfg.min_progress_m and not self._near(
            end, (NodeStatus.VISITED,), self.cfg.visit_radius_m * 0.5
        ):
            self.arrive(self.robot.observe(), previous=parent, travelled_m=travelled)
        elif travelled > 1e-3:
            # Stranded between nodes: go back to the parent so the graph stays truthful.
            self._move(*(g.pos(parent)[:2] - end[:2]))
            self.here = parent

    def _walk_to(self, goal: str) -> bool:
        """Follow traversed edges from the current node to ``goal``."""
        g = self.graph
        try:
            path = nx.shortest_path(g.traversed(), self.here, goal, weight="length")
        except (nx.NetworkXNoPath, nx.NodeNotFound):
            return False
        for nxt in path[1:]:
            if self.moves >= self.cfg.max_moves:
                return False
            p = g.pos(nxt)
            cur = self.pose.xyz
            res = self._move(p[0] - cur[0], p[1] - cur[1])
            if res.status != MoveStatus.REACHED:
                self.blocked += 1
                log.warning("blocked on a traversed edge towards %s", nxt)
                g.g.remove_edge(self.here, nxt) if g.g.has_edge(self.here, nxt) else None
                return False
            self.here = nxt
        return True

    def _move(self, dx: float, dy: float) -> MoveResult:
        self.moves += 1
        d = math.hypot(dx, dy)
        if d > 19.0:
            raise ExplorationError(f"refusing a {d:.1f} m single move; graph edges are short")
        res = self.robot.move_to(float(dx), float(dy))
        self.pose = res.pose
        self.trajectory.append(res.pose.xyz.copy())
        return res
