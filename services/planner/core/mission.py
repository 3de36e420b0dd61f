"""The mission loop of Section 4.3, one step at a time, against ports (no bus here).

    observe -> candidates (waypoint predictor) + backtrack + stop -> anticipated views (renderer)
    -> spatial map -> compressed history -> decide (policy) -> act (robot) -> event

The ports are small protocols; the planner service passes bus clients, tests pass in-process
objects (the simulator, the renderer core, the predictor core).
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np

from libs.scenegraph.text import floor_room_labels
from shared.jobs import Cancelled, JobContext, JobEnd
from shared.vln_metrics import EpisodeMetrics, episode_metrics
from shared.schemas import (
    CameraIntrinsics, Candidate, CandidateKind, Decision, JobEventKind, JobState, MapInfo, MissionEnd, MissionFinished,
    MissionOptions, MissionRequest, MissionStarted, MissionStep, MoveResult, Panorama, Pose, RenderResult,
    MapRoomLabel, SceneGraph, SpatialMapResult, SplatMode, ViewPose,
)

from .context import Ablation, OracleInfo, StepContext, build_candidate_views, with_stop_and_backtrack
from .errors import PlannerError
from .history import HistoryRecorder, action_for
from .policy import Policy

log = logging.getLogger(__name__)


class RobotPort(Protocol):
    def observe(self) -> Panorama: ...
    def move_to(self, dx_m: float, dy_m: float) -> MoveResult: ...
    def reset(self, pose: Pose | None = None) -> Pose: ...
    def geodesic_distance(self, start_m, goal_m) -> float: ...


class PredictorPort(Protocol):
    def predict(self, pano: Panorama) -> list[Candidate]: ...


class RendererPort(Protocol):
    def views(self, map_id: str, views: list[ViewPose], camera: CameraIntrinsics | None = None,
              with_labels: bool = True, **kw) -> RenderResult: ...

    def spatial_map(self, map_id: str, pose: Pose, trajectory_m: np.ndarray | None = None,
                    candidates: list[Candidate] | None = None, **kw) -> SpatialMapResult: ...


class SceneViewsPort(Protocol):
    """A simulator's true-scene views at given poses (``RobotClient.scene_views``, ``SimRobot.scene_views``)."""

    def scene_views(self, views: list[ViewPose], camera: CameraIntrinsics | None = None,
                    with_semantic: bool = True) -> RenderResult: ...


class AnticipationError(PlannerError):
    """Anticipated views could not be had as the mission asked (no such source, a mode not honoured)."""


@dataclass
class MapViews:
    """The method's anticipated views: the map rendered by the renderer (paper 4.3), in the mission's splat
    mode when it names one."""

    renderer: RendererPort

    def views(self, map_id: str, views: list[ViewPose], camera: CameraIntrinsics,
              splat_mode: SplatMode | None) -> RenderResult:
        if splat_mode is None:
            return self.renderer.views(map_id, views, camera)
        out = self.renderer.views(map_id, views, camera, splat_mode=splat_mode)
        if out.splat_mode != splat_mode:
            # An ablation must never run on views it did not ask for (a renderer older than the field).
            raise AnticipationError(f"asked the renderer for splat mode {splat_mode!r}, it rendered "
                                    f"{out.splat_mode or 'an unnamed mode'}")
        return out


@dataclass
class TrueSceneViews:
    """The control: the same poses ray-cast from the simulator's true scene (perfect geometry, colours and
    labels), so an ablation can tell wrong views from a policy that uses views wrongly. Simulator only."""

    robot: SceneViewsPort

    def views(self, map_id: str, views: list[ViewPose], camera: CameraIntrinsics,
              splat_mode: SplatMode | None) -> RenderResult:
        return self.robot.scene_views(views, camera)


# Where a mission's anticipated views come from (MissionOptions.anticipation_views), by name.
ANTICIPATION_SOURCES: dict[str, Callable[[Any, Any], Any]] = {
    "map": lambda robot, renderer: None if renderer is None else MapViews(renderer),
    "true-scene": lambda robot, renderer: TrueSceneViews(robot) if hasattr(robot, "scene_views") else None,
}


# emit(kind, state, step, data, images)
Emit = Callable[..., Any]


class MissionCancelled(Cancelled):
    """The mission's cancel was requested (the job runner ends it cancelled, at the step reached)."""


@dataclass
class MissionOutcome:
    state: JobState
    stop_called: bool
    steps: int
    trajectory_m: np.ndarray
    decisions: list[Decision] = field(default_factory=list)
    metrics: dict[str, Any] | None = None
    reason: str = ""
    step_latency_s: list[float] = field(default_factory=list)
    episode_metrics: EpisodeMetrics | None = None
    end: MissionEnd | None = None  # how the loop ended (policy stopped, boxed in, step budget)


def _thumb(rgb: np.ndarray, size_px: int) -> np.ndarray:
    return cv2.resize(np.ascontiguousarray(rgb), (size_px, size_px), interpolation=cv2.INTER_AREA)


def panorama_strip(pano: Panorama, height_px: int = 96) -> np.ndarray:
    """The 12 views side by side, left-most = leftmost direction (view i looks right of view i-1)."""
    views = [_thumb(v, height_px) for v in pano.rgb[::-1]]
    return np.concatenate(views, axis=1)


@dataclass
class MissionLoop:
    """Runs one mission; ``emit`` publishes events, ``cancel`` is polled between steps."""

    robot: RobotPort
    predictor: PredictorPort
    renderer: RendererPort | None
    policy: Policy
    emit: Emit
    cancel: threading.Event = field(default_factory=threading.Event)
    label_names: dict[int, str] = field(default_factory=dict)
    scene_graph: SceneGraph | None = None  # the map's, fetched at mission start (issue 32)
    thumb_px: int = 128
    jpeg: Callable[[np.ndarray], bytes] | None = None
    min_progress_m: float = 0.2  # a move shorter than this "went nowhere" (blocked at once)
    blocked_radius_m: float = 0.5

    def _known_blocked(self, blocked, pose: Pose, c: Candidate) -> bool:
        here = pose.xyz
        target = here + np.array([c.dx_m, c.dy_m, 0.0])
        r = self.blocked_radius_m
        return any(np.linalg.norm((here - a)[:2]) < r and np.linalg.norm((target - b)[:2]) < r for a, b in blocked)

    def anticipation_source(self, name: str):
        """The named source of anticipated views for this loop's robot and renderer."""
        make = ANTICIPATION_SOURCES.get(name)
        source = None if make is None else make(self.robot, self.renderer)
        if source is None:
            raise AnticipationError(f"no anticipated views from {name!r} here (known: {', '.join(ANTICIPATION_SOURCES)}; "
                                    "map needs a renderer, true-scene a simulator)")
        return source

    def run(self, mission_id: str, instruction: str, map_id: str, opts: MissionOptions) -> MissionOutcome:
        ablation = Ablation(anticipation=opts.anticipation, anticipation_hfov_deg=opts.anticipation_hfov_deg,
                            spatial_map=opts.spatial_map)
        anticipator = self.anticipation_source(opts.anticipation_views) if opts.anticipation else None
        if opts.start_pose is not None:
            self.robot.reset(opts.start_pose)
        self.policy.reset(mission_id)
        history = HistoryRecorder()
        visited: list[tuple[float, float, float]] = []  # nodes before the current one (backtrack target)
        decisions: list[Decision] = []
        latencies: list[float] = []
        goal = np.asarray(opts.goal_m, float) if opts.goal_m is not None else None
        reference = np.asarray(opts.reference_path_m, float) if opts.reference_path_m else None
        oracle = (OracleInfo(goal_m=goal, reference_path_m=reference, geodesic=self.robot.geodesic_distance)
                  if goal is not None else None)
        # (from, to) of moves that went nowhere: offering them again would loop forever.
        blocked: list[tuple[np.ndarray, np.ndarray]] = []
        t_obs = time.perf_counter()
        pano = self.robot.observe()
        observe_s = time.perf_counter() - t_obs
        move_s = 0.0  # a step's timings hold the move and observation that led to it (none before step 0)
        trajectory = [pano.pose.xyz]
        stop_called = False
        step = 0
        boxed_in_at: int | None = None  # last step at which stop was the only action left
        self.emit(JobEventKind.STARTED, JobState.RUNNING, step=0,
                  data=MissionStarted(pose=pano.pose, instruction=instruction, map_id=map_id, options=opts))
        for step in range(opts.max_steps):
            if self.cancel.is_set():
                raise MissionCancelled()
            t0 = time.perf_counter()
            timings: dict[str, float] = {}
            pose = pano.pose
            waypoints = [c for c in self.predictor.predict(pano) if not self._known_blocked(blocked, pose, c)]
            t1 = time.perf_counter()
            timings["candidates_s"] = t1 - t0
            previous = visited[-1] if visited else None
            if previous is not None and self._known_blocked(blocked, pose, _towards(pose, previous)):
                previous = None  # the way back went nowhere already; offering it again would loop
            cands = with_stop_and_backtrack(waypoints, pose, previous)
            if len(cands) == 1:
                boxed_in_at = step
            movable = [c for c in cands if c.kind != CandidateKind.STOP]
            # The spatial map is asked for first and drawn while the views render (the renderer serves
            # the two on their own workers; two cores share them): the step waits for the longer, not both.
            smap_job = None
            if ablation.spatial_map and self.renderer is not None:
                draw = self.renderer.spatial_map
                if self.scene_graph is not None and self.scene_graph.rooms:
                    # The graph's room instances ("bedroom 2", as the prompt's text names them), not the
                    # cloud's one name per room type.
                    draw = functools.partial(draw, room_labels=[
                        MapRoomLabel(name=n, x_m=x, y_m=y) for n, x, y in floor_room_labels(self.scene_graph, pose.xyz)])
                smap_job = _in_background(draw, map_id, pose, np.asarray(trajectory), cands)
            render = None
            if anticipator is not None and movable:
                views = [ViewPose(position_m=(pose.position_m[0] + c.dx_m, pose.position_m[1] + c.dy_m,
                                              pose.position_m[2]),
                                  heading_rad=math.atan2(c.dy_m, c.dx_m)) for c in movable]
                cam = CameraIntrinsics(hfov_deg=ablation.anticipation_hfov_deg)
                render = anticipator.views(map_id, views, cam, opts.anticipation_splat_mode)
            timings["anticipation_s"] = time.perf_counter() - t1
            smap, timings["spatial_map_s"] = None, 0.0
            if smap_job is not None:
                smap, timings["spatial_map_s"] = smap_job.result()  # its own duration (it overlapped the views)
            ctx = StepContext(
                instruction=instruction, step=step, pose=pose, candidates=build_candidate_views(cands, pano, render),
                trajectory_m=np.asarray(trajectory), history=history.compressed(),
                spatial_map_rgb=None if smap is None else smap.image, label_names=self.label_names,
                ablation=ablation, mission_id=mission_id, max_steps=opts.max_steps, panorama=pano, oracle=oracle,
                scene_graph=self.scene_graph,
            )
            t4 = time.perf_counter()
            timings["observe_s"] = observe_s
            timings["move_s"] = move_s
            # The paper's "global perception" plus the observation: what a step costs before the LLM.
            timings["prompt_ready_s"] = t4 - t0 + observe_s
            latencies.append(timings["prompt_ready_s"])
            decision = self.policy.decide(ctx)
            t5 = time.perf_counter()
            timings["decide_s"] = t5 - t4
            decisions.append(decision)
            chosen = ctx.candidate(decision.candidate_index)
            self._emit_step(step, pano, ctx, decision, timings, smap)
            if chosen.kind == CandidateKind.STOP:
                stop_called = True
                break
            history.record(step, pano.rgb[0], action_for(chosen.candidate))
            c = chosen.candidate
            t_move = time.perf_counter()
            result = self.robot.move_to(c.dx_m, c.dy_m)
            move_s = time.perf_counter() - t_move
            moved = float(np.hypot(*(result.pose.xyz - pose.xyz)[:2]))
            if moved < self.min_progress_m:
                blocked.append((pose.xyz, pose.xyz + np.array([c.dx_m, c.dy_m, 0.0])))
            elif chosen.kind == CandidateKind.BACKTRACK:
                visited.pop()
            else:
                visited.append(pose.position_m)
            trajectory.append(result.pose.xyz)
            t_obs = time.perf_counter()
            pano = self.robot.observe()
            observe_s = time.perf_counter() - t_obs
        state = JobState.SUCCEEDED if stop_called else JobState.FAILED
        reason = "" if stop_called else f"step budget of {opts.max_steps} exhausted without a stop"
        end = MissionEnd.POLICY_STOPPED if stop_called else MissionEnd.MAX_STEPS
        if stop_called and boxed_in_at == len(decisions) - 1:
            end = MissionEnd.NO_WAY_TO_MOVE
            # The policy had no other choice: say so, the stop is not a judgement that the goal is here.
            reason = (f"boxed in: no way forward or back at step {boxed_in_at} (the waypoint predictor found "
                      "no reachable candidate), so the mission stopped where it was")
            log.warning("mission %s: %s", mission_id, reason)
        m = None
        traj = np.asarray(trajectory)
        if goal is not None:
            m = episode_metrics(traj, goal, geodesic=self.robot.geodesic_distance, stop_called=stop_called,
                                reference_path_m=reference)
        return MissionOutcome(state, stop_called, len(decisions), traj, decisions, m.to_dict() if m else None,
                              reason, latencies, m, end)

    def _emit_step(self, step: int, pano: Panorama, ctx: StepContext, decision: Decision,
                   timings: dict[str, float], smap: SpatialMapResult | None) -> None:
        images: dict[str, bytes] = {}
        if self.jpeg is not None:
            images["panorama"] = self.jpeg(panorama_strip(pano))
            if smap is not None:
                images["map"] = self.jpeg(smap.image)
            for v in ctx.candidates:
                if v.observed_rgb is not None:
                    images[f"cand_{v.index}_observed"] = self.jpeg(_thumb(v.observed_rgb, self.thumb_px))
                if v.anticipated_rgb is not None:
                    images[f"cand_{v.index}_anticipated"] = self.jpeg(_thumb(v.anticipated_rgb, self.thumb_px))
        self.emit(JobEventKind.STEP, JobState.RUNNING, step=step, images=images, data=MissionStep(
            pose=pano.pose, candidates=[v.candidate for v in ctx.candidates], decision=decision,
            timings_s={k: round(v, 4) for k, v in timings.items()}, usage=self.policy.usage.model_copy(),
        ))


def _in_background(fn: Callable[..., Any], *args) -> Future:
    """``fn(*args)`` on a thread of its own: a future of (its result, its seconds). A thread a step (tens
    of microseconds) rather than a pool: nothing to shut down however the mission ends."""
    fut: Future = Future()

    def job() -> None:
        t0 = time.perf_counter()
        try:
            fut.set_result((fn(*args), time.perf_counter() - t0))
        except BaseException as exc:  # handed to the step that waits for it
            fut.set_exception(exc)

    threading.Thread(target=job, name="spatial-map", daemon=True).start()
    return fut


def _towards(pose: Pose, target_m) -> Candidate:
    """A candidate from ``pose`` to the floor point ``target_m`` (for the blocked-move check)."""
    return Candidate(index=0, kind=CandidateKind.BACKTRACK, dx_m=float(target_m[0]) - pose.position_m[0],
                     dy_m=float(target_m[1]) - pose.position_m[1])


class MapInfoPort(Protocol):
    def info(self, map_id: str, version: int | None = None) -> MapInfo: ...


def run_mission(ctx: JobContext, req: MissionRequest, *, robot: RobotPort, predictor: PredictorPort,
                renderer: RendererPort | None, maps: MapInfoPort, policy: Policy,
                jpeg: Callable[[np.ndarray], bytes] | None = None) -> JobEnd:
    """The mission job (a body for :class:`shared.jobs.JobRunner`): the loop, then its typed end.

    A failed mission (step budget exhausted) carries its cause as the error; a stop with a caveat (boxed
    in) as the reason."""
    info = maps.info(req.map_id)
    graph = None
    if hasattr(maps, "scene_graph"):
        try:
            graph = maps.scene_graph(req.map_id, info.version)
        except Exception as exc:  # a store without graphs, a timeout: the policy navigates locally
            log.warning("mission %s: no scene graph for map %s (%s)", req.mission_id, req.map_id, exc)
    loop = MissionLoop(robot=robot, predictor=predictor, renderer=renderer, policy=policy,
                       emit=lambda kind, state, *, step=0, data=None, images=None:
                       ctx.emit(kind, data, step=step, images=images),
                       cancel=ctx.cancel, label_names=info.label_names, jpeg=jpeg, scene_graph=graph)
    out = loop.run(req.mission_id, req.instruction, req.map_id, req.options)
    failed = out.state == JobState.FAILED
    return JobEnd(out.state, MissionFinished(
        stop_called=out.stop_called, steps=out.steps, outcome=out.end,
        success=None if out.metrics is None else bool(out.metrics["success"]),
        trajectory_m=[tuple(p) for p in out.trajectory_m.tolist()], metrics=out.metrics, usage=policy.usage.model_copy(),
        step_latency_s=[round(x, 4) for x in out.step_latency_s],
        reason="" if failed else out.reason, error=out.reason if failed else ""), step=out.steps)

