"""The exploration job: Algorithm 1 on a robot, its region tours recorded, and the map built from them.

A job body for :class:`shared.jobs.JobRunner`, written against ports (a robot that records tours
remotely, a map builder, two publishers), so the mapper service only wires bus clients into it:

1. frontier DFS over the waypoint predictor's candidates, regions, hubs and tours (:func:`discover`);
2. one recorded tour per region: the robot publishes the frames, the reconstructor collects them; a
   region whose start cannot be reached is skipped and reported, the map is built from the rest;
3. the map build, itself a job of the reconstructor, whose progress is relayed as this job's.

A cancel (the job's flag) is seen before every exploration step, before every move of a tour, and
while the build runs: then the build is cancelled on the reconstructor too, and waited for, so the
job ends ``cancelled`` (with the stage it was in) only once the build has stored nothing. A build that
had already stored its map when the cancel reached it is whole: the job then ends succeeded with it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from shared.jobs import JobContext, JobEnd
from shared.schemas import (
    BuildMapRequest, ExplorationFinished, ExplorationOutcome, ExplorationProgress, ExplorationRequest, JobEvent, JobState, MapBuildProgress,
    MapInfo, NavGraph, OdomCorrection, RecordReply, SceneSummary, Tour, TourRecording, UsageData,
)

from .discovery import DiscoveryConfig, discover, discovery_config
from .explorer import ExplorationStep
from .execute import RegionRecording, TourRobot, execute_tours
from .tours import TourConfig

log = logging.getLogger(__name__)


class RecordingRobot(TourRobot, Protocol):
    """A robot whose tour recordings go elsewhere (robot-io publishes them): after each recording,
    ``last_recording`` says what was recorded and how many frames."""

    last_recording: RecordReply | None

    def scene(self) -> SceneSummary: ...


class MapBuilder(Protocol):
    def build(self, req: BuildMapRequest, *, on_event: Callable[[JobEvent], None] | None = None,
              cancel: threading.Event | None = None) -> MapInfo:
        """Build to the end; ``cancel`` set cancels the build too and raises :class:`shared.jobs.Cancelled`
        once it ended so."""
        ...


# Where each stage sits in the exploration's progress (0-1): discovery, tours, the map build.
_TOURS_AT, _BUILD_AT, _BUILD_SPAN = 0.3, 0.8, 0.2


def request_discovery_config(req: ExplorationRequest) -> DiscoveryConfig:
    """What an exploration request asks for: ``options.profile`` (:data:`DISCOVERY_PROFILES`, e.g.
    ``cluttered-scan`` for a real scan), ``options.discovery`` overrides on top of it, and
    ``max_steps`` as a hard cap (otherwise the budget scales with the area discovered). Raises
    ``KeyError`` / ``ValueError`` for options the mapper refuses before accepting the job."""
    profile = req.options.get("profile", "default")
    overrides = req.options.get("discovery", {})
    if not isinstance(profile, str) or not isinstance(overrides, dict):
        raise ValueError("options.profile must be a profile name and options.discovery an object")
    cfg = discovery_config(profile, overrides)
    if req.max_steps is not None:
        cfg.exploration.max_steps = req.max_steps
    return cfg


def explore(ctx: JobContext, req: ExplorationRequest, *, robot: RecordingRobot, maps: MapBuilder,
            publish_graph: Callable[[NavGraph], None], publish_tour: Callable[[Tour], None],
            tour_rate_hz: float) -> JobEnd:
    t0 = time.perf_counter()
    cfg = request_discovery_config(req)
    ctx.progress(ExplorationProgress(stage="exploring", progress=0.02, message="frontier DFS over waypoints"))
    disc = discover(robot, cfg, checkpoint=ctx.check_cancelled, on_step=StepReporter(ctx))
    ctx.check_cancelled()
    nav_graph = disc.nav_graph()
    publish_graph(nav_graph)
    for tour in disc.tour_messages():
        publish_tour(tour)
    nodes = len(disc.result.graph.graph)
    timings_s = {k: round(v, 3) for k, v in disc.timings_s.items()}
    n_tours = max(1, len(disc.tours))
    outcome = ExplorationOutcome(**disc.result.summary())
    ended = describe_outcome(outcome)
    touring = f"recording {len(disc.tours)} region tours{tour_range_phrase(outcome, cfg.tours)}"
    ctx.progress(ExplorationProgress(stage="touring", progress=_TOURS_AT, nodes=nodes, regions=len(disc.tours),
                                     timings_s=timings_s, outcome=outcome,
                                     message=f"explored {nodes} nodes ({ended}); {touring}"))

    recordings: list[TourRecording] = []
    skipped: list[int] = []

    def tours_progress() -> float:
        return _TOURS_AT + (_BUILD_AT - _TOURS_AT) * (len(recordings) + len(skipped)) / n_tours

    recorded: list[tuple[RegionRecording, Any]] = []

    def tour_recording(rec: RegionRecording, last: Any) -> TourRecording:
        # Robot-io publishes the frames with its odometry poses: the start pose goes with them, and
        # the mapper's corrections beside them, for the reconstructor to apply (issue 33).
        start = rec.corrections[0][1].odom(rec.start_pose) if rec.corrections else rec.start_pose
        corrections = [OdomCorrection(since_s=t, dx_m=c.dx_m, dy_m=c.dy_m, dyaw_rad=c.dyaw_rad)
                       for t, c in rec.corrections if not c.identity or len(rec.corrections) > 1]
        return TourRecording(exploration_id=req.exploration_id, recording=last.recording, region=rec.region,
                             start_pose=start, frame_count=last.frame_count, odom_corrections=corrections,
                             odom_corrections_interpolated=rec.interpolated and bool(corrections))

    def on_recording(rec: RegionRecording) -> None:
        last = robot.last_recording
        if last is None:
            raise RuntimeError(f"region {rec.region}: the robot reported no recording")
        recorded.append((rec, last))
        recordings.append(tour_recording(rec, last))
        ctx.progress(ExplorationProgress(
            stage="touring", progress=tours_progress(), region=rec.region, frames=last.frame_count,
            message=f"region {rec.region}: {last.frame_count} frames ({len(recordings)}/{len(disc.tours)})"))
        ctx.check_cancelled()

    def on_skip(pt, exc) -> None:
        skipped.append(pt.tour.region)
        ctx.progress(ExplorationProgress(stage="touring", progress=tours_progress(), region=pt.tour.region,
                                         message=f"region {pt.tour.region} skipped: {exc}"))

    execute_tours(robot, disc.tours, disc.scene, rate_hz=tour_rate_hz, on_recording=on_recording, on_skip=on_skip,
                  checkpoint=ctx.check_cancelled, sidestep=cfg.exploration.sidestep)
    # The pose graph re-placed the recordings once all tours were in (execute.replace_recordings):
    # their corrections are the final ones.
    recordings[:] = [tour_recording(rec, last) for rec, last in recorded]
    if disc.scene.localiser is not None:
        # The correction the robot ends its tours with: against the robot's own truth, where one knows
        # it (a simulator, the ROS 2 stand-in's log), what is left of the drift.
        c = disc.scene.localiser.correction
        log.info("localisation after the tours: map <- odom (%.3f, %.3f) m, %.2f deg", c.dx_m, c.dy_m,
                 math.degrees(c.dyaw_rad))
    if not recordings:
        raise RuntimeError(f"no region tour could be recorded ({len(skipped)} skipped)")
    ctx.progress(ExplorationProgress(stage="reconstructing", progress=_BUILD_AT,
                                     message=f"reconstructing {len(recordings)} regions"))

    def on_build_event(ev: JobEvent) -> None:
        if isinstance(ev.data, MapBuildProgress):
            ctx.progress(ExplorationProgress(stage="reconstructing", progress=_BUILD_AT + _BUILD_SPAN * ev.data.progress
                                             * 0.99, region=ev.data.region, regions=ev.data.regions,
                                             message=ev.data.message))

    scene = robot.scene()
    ctx.check_cancelled()
    info = maps.build(BuildMapRequest(
        build_id=req.exploration_id, exploration_id=req.exploration_id, map_id=req.map_id, recordings=recordings,
        reconstruction=req.reconstruction, options=req.options.get("reconstruction", {}),
        label_names=scene.label_names, navigation=nav_graph,
        pose_graph=None if disc.scene.localiser is None else disc.scene.localiser.graph_summary(), source=f"exploration {req.exploration_id} of {scene.scene} ({ended})"),
        on_event=on_build_event, cancel=ctx.cancel)
    return JobEnd(JobState.SUCCEEDED, ExplorationFinished(
        map_id=info.map_id, version=info.version, points=info.point_count, regions=len(recordings),
        skipped_regions=skipped, nodes=nodes, timings_s=timings_s, outcome=outcome,
        wall_s=round(time.perf_counter() - t0, 2), usage=labelling_usage(info)))


def labelling_usage(info: MapInfo) -> UsageData:
    """What the reconstructor's labeller spent naming the map's rooms, as the ledger counts usage."""
    if info.labelling is None:
        return UsageData()
    return UsageData(**info.labelling.model_dump(include=set(UsageData.model_fields)))


class StepReporter:
    """Turns the explorer's per-panorama standing into progress events: a real robot takes seconds
    per panorama, and an exploration of a house hundreds of them, so the exploring stage must show
    that it moves. Its share of the progress bar (0.02 to ``_TOURS_AT``) grows with the visited share
    of the nodes known (visited + open frontiers), never backwards; the coverage estimate, refreshed
    every few seconds only, is carried between refreshes."""

    def __init__(self, ctx: JobContext):
        self.ctx = ctx
        self.progress = 0.02
        self.coverage: float | None = None

    def __call__(self, st: ExplorationStep) -> None:
        if st.coverage_estimate is not None:
            self.coverage = st.coverage_estimate
        known = st.visited + st.open_frontiers
        self.progress = max(self.progress, 0.02 + (_TOURS_AT - 0.03) * st.visited / max(1, known))
        left = f"~{st.time_left_s:.0f} s left" if st.step > 1 else "time left unknown yet"
        cover = f"coverage ~{self.coverage:.0%}, " if self.coverage is not None else ""
        self.ctx.progress(ExplorationProgress(
            stage="exploring", progress=round(self.progress, 4), step=st.step, visited=st.visited, seen=st.seen,
            open_frontiers=st.open_frontiers, floors=st.floors, coverage_estimate=self.coverage,
            elapsed_s=round(st.elapsed_s, 2), time_left_s=round(st.time_left_s, 1) if st.step > 1 else None,
            message=(f"step {st.step}/{st.step_budget}: {st.visited} visited, {st.seen} seen, "
                     f"{st.open_frontiers} open frontiers, {st.floors} floor{'s' if st.floors != 1 else ''}, "
                     f"{cover}{st.elapsed_s:.0f} s elapsed, {left}")), step=st.step)


def tour_range_phrase(outcome: ExplorationOutcome, tours: TourConfig) -> str:
    """Why the tours stand closer than configured, where they do: the robot declared depth noise."""
    range_m = tours.vis_radius_for(outcome.depth_noise_rel)
    if range_m >= tours.vis_radius_m:
        return ""
    return f" (hubs count what lies within {range_m:.1f} m: the robot declares depth noise {outcome.depth_noise_rel:g})"


def describe_outcome(outcome: ExplorationOutcome) -> str:
    """How the exploration ended, in words, for the events and the map's source line."""
    if outcome.finished:
        ended = "no frontier left"
    elif outcome.stop_reason != "exhausted":
        ended = f"stopped by its {outcome.stop_reason} budget after {outcome.steps} of {outcome.step_budget} steps"
    elif outcome.open_stairs:
        ended = f"{outcome.open_stairs} stair nodes lead past the explored floors"
    else:
        ended = f"{outcome.open_frontiers} frontiers seen but never tried"
    return f"{ended}, coverage estimate {outcome.coverage_estimate:.0%}"
