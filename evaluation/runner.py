"""The experiment runner: an R2R-CE-format episode file through the running system, via the gateway.

For each scene (episodes grouped by ``scene_id``, in file order) it switches robot-io to the scene,
obtains a map (``reconstructed``: ``POST /explorations``; ``curated``: a cloud sampled from the scene
mesh uploaded with ``POST /maps``; either cached per scene and source), then runs every episode as a
mission (start pose, goal and reference path in the options, a deterministic seed per episode), waits
for its end and appends one JSON line to ``results.jsonl``. Episodes already ``done`` in that file are
not run again, so an interrupted run resumes where it stopped. Episodes whose scene file is missing are
recorded as ``skipped`` with the reason. The summary (Markdown + CSV) is recomputed from the log.

A budget (dollars, tokens, wall seconds: :class:`evaluation.ledger.Budget`) is watched while missions
run: when it is reached, every mission in flight is cancelled through its gateway and recorded as
``stopped`` (neither a policy failure nor a system error), no robot starts another episode, and the
summary says what ended the run and what it spent. A robot that is exploring a scene to build its map
when the budget is reached has that exploration cancelled through its gateway too (its map build stores
nothing), and the scene's episodes count as not started. A resumed run (with a larger budget) runs the
stopped episodes again.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import queue
import re
import threading
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from evaluation.clouds import CURATED_DENSITY_PER_M2
from evaluation.errors import (
    ConfigError, EvaluationError, ExplorationStopped, GatewayError, MapUnavailable, MissionTimeout, SceneSwitchError,
)
from evaluation.gateway_client import TERMINAL_STATES, GatewayClient
from evaluation.ledger import Budget, Spent, ledger_markdown, stage_totals, step_ledger
from shared.vln_metrics import MetricsError
from evaluation.results import EpisodeResult, ResultsLog, metrics_from_dict, skipped_report, summary_row, write_tables
from libs.world import Episode, GroundTruth, SceneNotFoundError
from libs.world.scene import is_generated_spec
from shared.schemas import MissionFinished, MissionOptions, SceneSummary, UsageData

log = logging.getLogger(__name__)

RESULTS_FILE = "results.jsonl"
SUMMARY_STEM = "summary"
RUN_FILE = "run.json"


class MapSource(StrEnum):
    """Where a scene's map comes from (the paper's ablation of Table 4)."""

    RECONSTRUCTED = "reconstructed"  # the agent explores and reconstructs (the paper's method)
    CURATED = "curated"  # a cloud sampled from the scene mesh (the dataset's human-curated scan)


class RunConfig(BaseModel):
    """Everything that defines an evaluation run. ``experiment_key()`` fields must not change on resume."""

    model_config = ConfigDict(extra="forbid")

    policy: str = Field("heuristic", description="planner policy backend (heuristic, oracle, openai, replay)")
    policy_config: dict[str, Any] = Field(default_factory=dict, description="the policy backend's typed config")
    max_steps: int = Field(40, ge=1, le=500, description="decisions per episode before it counts as not stopped")
    anticipation: bool = True
    anticipation_hfov_deg: float = Field(90.0, ge=30.0, le=150.0)
    anticipation_splat_mode: Literal["paper", "visibility"] | None = Field(
        None, description="the renderer's splat mode for anticipated views (None: the renderer's default)")
    anticipation_views: Literal["map", "true-scene"] = Field(
        "map", description="anticipated views rendered from the map, or ray-cast from the true scene (simulator)")
    spatial_map: bool = True
    map_source: MapSource = MapSource.RECONSTRUCTED
    seed: int = Field(0, description="run seed; each episode's mission seed derives from it and the episode id")
    reference: Literal["auto", "gt", "episode"] = Field(
        "auto", description="nDTW reference: gt = the dense *_gt.json.gz locations (VLN-CE), episode = "
                            "reference_path; auto = gt when the file exists")
    limit: int | None = Field(None, ge=1, description="only the first N episodes of the file")
    scenes_dir: Path | None = Field(None, description="where mesh scene ids (e.g. mp3d/X/X.glb) are looked up")
    mission_timeout_s: float = Field(1800.0, gt=0)
    exploration_timeout_s: float = Field(7200.0, gt=0)
    exploration_max_steps: int = Field(400, ge=1, le=10_000)
    reconstruction: str = Field("rgbd", description="regional reconstruction backend of explorations")
    curated_density_per_m2: float = Field(CURATED_DENSITY_PER_M2, gt=0, allow_inf_nan=False)
    curated_max_points: int = Field(1_000_000, ge=1000)
    poll_s: float = Field(0.5, gt=0, le=30)
    retry_errors: bool = Field(True, description="on resume, run episodes that ended in an error again")
    record: bool = Field(False, description="record every mission (.rrd) and keep a copy in <run>/recordings/")
    # Output only, so not in experiment_key(): a run resumed with plots switched on or off is the same experiment.
    plots: bool = Field(True, description="draw a top-down PNG per episode into <run>/plots/ (about 0.1 s of CPU "
                                          "each); off, summary.md says so and links none")
    budget_usd: float | None = Field(None, gt=0, allow_inf_nan=False,
                                     description="stop the run once its dollars (every attempt, the missions in "
                                                 "flight included) reach this; see evaluation.ledger.Budget")
    budget_tokens: int | None = Field(None, gt=0, description="the same for LLM tokens (prompt + completion)")
    budget_wall_s: float | None = Field(None, gt=0, allow_inf_nan=False,
                                        description="stop the run once this call has run this many seconds")
    stop_wait_s: float = Field(120.0, gt=0, le=3600, allow_inf_nan=False,
                               description="how long a mission or exploration cancelled (by the budget or a "
                                           "timeout) may take to end (the planner ends a mission between steps, "
                                           "the mapper an exploration within a step or by cancelling its map "
                                           "build)")

    def experiment_key(self) -> dict[str, Any]:
        """The settings a results file is only valid for (resuming with others would mix experiments)."""
        return self.model_dump(mode="json", include={
            "policy", "policy_config", "max_steps", "anticipation", "anticipation_hfov_deg", "spatial_map",
            "map_source", "seed", "reference", "anticipation_splat_mode", "anticipation_views"})


def episode_seed(run_seed: int, episode_id: Any) -> int:
    """A mission seed from the run seed and the episode id: stable across runs, machines and order."""
    return zlib.crc32(f"{run_seed}:{episode_id}".encode()) & 0x7FFFFFFF


def group_by_scene(episodes: Sequence[Episode]) -> dict[str, list[Episode]]:
    """Episodes per scene id, scenes in order of first appearance, episodes in file order."""
    groups: dict[str, list[Episode]] = {}
    for e in episodes:
        groups.setdefault(e.scene_id, []).append(e)
    return groups


_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def map_id_for(scene_id: str, source: MapSource | str, prefix: str = "eval") -> str:
    """A gateway-safe map id (``[A-Za-z0-9][A-Za-z0-9_.-]{0,63}``), readable and unique per scene+source."""
    slug = _UNSAFE.sub("_", scene_id.rsplit("/", 1)[-1]).strip("_.-") or "scene"
    digest = hashlib.sha1(f"{scene_id}|{source}".encode()).hexdigest()[:8]
    head = f"{prefix}-{MapSource(source).value}-"
    return f"{head}{slug[: 64 - len(head) - 9]}-{digest}"


class SceneLoader(Protocol):
    """Switches the robot's scene (``shared.clients.RobotClient`` satisfies it)."""

    def load_scene(self, scene: str) -> SceneSummary: ...


class SceneMapIndex:
    """Which stored map serves a scene and map source (scene + source -> map id), persisted as JSON and
    shared by the runs of a preset, so a house is explored or uploaded once."""

    def __init__(self, path: Path | str):
        self.path = Path(path)
        self._lock = threading.Lock()
        self._data: dict[str, str] = {}
        if self.path.is_file():
            try:
                self._data = dict(json.loads(self.path.read_text(encoding="utf-8")))
            except ValueError as exc:
                raise ConfigError(f"{self.path}: not a scene map index ({exc})") from None

    @staticmethod
    def _key(scene_id: str, source: MapSource | str) -> str:
        return f"{MapSource(source).value}|{scene_id}"

    def get(self, scene_id: str, source: MapSource | str) -> str | None:
        return self._data.get(self._key(scene_id, source))

    def put(self, scene_id: str, source: MapSource | str, map_id: str) -> None:
        with self._lock:
            self._data[self._key(scene_id, source)] = map_id
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps(self._data, indent=1, sort_keys=True), encoding="utf-8")
            tmp.replace(self.path)


@dataclass
class RunReport:
    """What one :meth:`EvalRunner.run` did and where it wrote it."""

    out_dir: Path
    results: list[EpisodeResult]  # latest result of every selected episode, in file order
    row: dict[str, Any]  # the summary row (see :data:`evaluation.results.COLUMNS`)
    ran: int = 0  # episodes run by this call
    resumed: int = 0  # episodes found done in the log and not run again
    wall_s: float = 0.0
    tables: tuple[Path, Path] | None = None
    maps: dict[str, str] = field(default_factory=dict)  # scene -> map id used
    stopped: str = ""  # why the run stopped before its last episode (the budget), "" when it did not
    spent: Spent = field(default_factory=Spent)  # every attempt of the selected episodes, this call's included


def shard_scenes(groups: dict[str, list[Episode]], lanes: int) -> list[list[str]]:
    """Scenes per robot: whole scenes only (a robot loads a scene once), the largest first to the robot
    with the fewest episodes so far (ties: the lowest robot). Deterministic in the groups' order."""
    shards: list[list[str]] = [[] for _ in range(max(1, lanes))]
    load = [0] * len(shards)
    for scene in sorted(groups, key=lambda k: -len(groups[k])):  # stable: file order among equals
        i = min(range(len(shards)), key=lambda j: (load[j], j))
        shards[i].append(scene)
        load[i] += len(groups[scene])
    return [[sc for sc in groups if sc in set(sh)] for sh in shards]  # each robot keeps file order


@dataclass
class Lane:
    """One robot the runner drives concurrently with the others: its gateway and scene switcher."""

    gateway: GatewayClient
    scenes: SceneLoader | None


class EvalRunner:
    """Runs episodes through the gateway; see the module docstring.

    Args:
        gateway: the gateway's HTTP client.
        scenes: switches robot-io's scene; None means the robot already holds the (single) scene.
        config: the run's settings.
        out_dir: ``results.jsonl``, ``summary.md/.csv``, ``run.json`` and (unless ``map_cache`` is given)
            ``maps.json`` go here.
        map_cache: shared map ids (presets pass one for all their runs).
        label: the summary row's label.
        progress: show a tqdm progress bar (stderr).
        scene_builder: ``scene_builder(spec, scenes_dir) -> Scene`` for curated clouds (default: robot-io's
            :func:`load_scene`, the same scenes the simulator loads).
        lanes: more robots (each a gateway and scene switcher: a light gateway per robot, the planner and
            other services shared by all robots or not, on any host);
            the scenes are sharded over ``gateway`` + these (:func:`shard_scenes`) and run concurrently.
            Every result is the same whatever the number of robots: each episode runs alone on its robot
            with its own seed.
        clock: seconds for the wall-time budget (``budget_wall_s``); the default is the monotonic clock.
    """

    def __init__(self, gateway: GatewayClient, scenes: SceneLoader | None, config: RunConfig, out_dir: Path | str,
                 *, map_cache: SceneMapIndex | None = None, label: str = "all", progress: bool = True,
                 scene_builder: Callable[[str, Path | None], Any] | None = None, lanes: Sequence[Lane] = (),
                 clock: Callable[[], float] = time.monotonic):
        self.gateway, self.scenes, self.config = gateway, scenes, config
        self.lanes = [Lane(gateway, scenes), *lanes]
        self._stop = threading.Event()  # set: no robot starts another episode
        self._budget = Budget()  # the run's (see run()); unlimited for a lone run_episode()
        self._explorations_stopped: list[ExplorationStopped] = []  # this run's, every robot's (shared list)
        self.out_dir = Path(out_dir)
        self.log = ResultsLog(self.out_dir / RESULTS_FILE)
        self.maps = map_cache or SceneMapIndex(self.out_dir / "maps.json")
        self.label, self.progress = label, progress
        self.scene_builder = scene_builder
        self.clock = clock

    # --- the run -------------------------------------------------------------------------------------
    def _check_resume(self) -> None:
        path = self.out_dir / RUN_FILE
        key = self.config.experiment_key()
        if path.is_file():
            # A setting added after the run was made reads as its default (what that run did).
            old = {**RunConfig().experiment_key(), **json.loads(path.read_text(encoding="utf-8")).get("experiment", {})}
            if old != key:
                diff = {k: (old.get(k), v) for k, v in key.items() if old.get(k) != v}
                raise ConfigError(f"{self.out_dir} holds results of another experiment ({diff} as (old, new)); "
                                  "use another --out")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"experiment": key, "config": self.config.model_dump(mode="json")}, indent=1),
                        encoding="utf-8")

    def select(self, episodes: Sequence[Episode]) -> list[Episode]:
        eps = list(episodes)
        ids = [str(e.episode_id) for e in eps]
        if len(set(ids)) != len(ids):
            raise ConfigError("the episode file repeats episode ids; results are keyed by id")
        return eps[: self.config.limit] if self.config.limit else eps

    def pending(self, episodes: Sequence[Episode], prior: dict[str, EpisodeResult]) -> list[Episode]:
        """Episodes still to run: not done, and not errored unless errors are retried."""
        out = []
        for e in episodes:
            r = prior.get(str(e.episode_id))
            if r is None or r.status in ("skipped", "stopped") or (r.status == "error" and self.config.retry_errors):
                out.append(e)
        return out

    def run(self, episodes: Sequence[Episode], gt: dict[str, GroundTruth] | None = None) -> RunReport:
        """Run (or resume) the episodes; returns the report and writes the summary tables."""
        t0 = time.monotonic()
        cfg = self.config
        if cfg.reference == "gt" and not gt:
            raise ConfigError("reference='gt' needs the episodes' ground-truth file (*_gt.json.gz)")
        selected = self.select(episodes)
        self._check_resume()
        prior = self.log.load()
        todo = self.pending(selected, prior)
        groups = group_by_scene(todo)
        if any(lane.scenes is None for lane in self.lanes) and len(groups) > 1:
            raise SceneSwitchError(f"{len(groups)} scenes to run but no way to switch scenes (give the runner a "
                                   "bus connection to robot-io)")
        resumed = len(selected) - len(todo)
        if resumed:
            log.info("resuming: %d of %d episodes already done", resumed, len(selected))
        bar = _progress(len(todo), f"{self.label} ({resumed} done before)" if resumed else self.label,
                        self.progress)
        ran = 0
        maps: dict[str, str] = {}
        stats = {"done": 0, "success": 0}
        selected_ids = {str(e.episode_id) for e in selected}
        # Every attempt counts: an episode stopped by the budget or retried after an error was paid for.
        budget = Budget(cfg.budget_usd, cfg.budget_tokens, cfg.budget_wall_s,
                        spent=sum((Spent.of(r) for r in self.log.attempts() if r.episode_id in selected_ids),
                                  Spent()), clock=self.clock)
        self._budget = budget
        self._explorations_stopped.clear()
        why = budget.exceeded() if todo else ""
        n_stopped = 0
        try:
            for scene_id, result in ([] if why else self._concurrent(groups, gt or {}, maps)):
                self.log.append(result)
                ran += 1
                budget.settle(result.mission_id, Spent.of(result))
                n_stopped += result.status == "stopped"
                if result.status == "done":
                    stats["done"] += 1
                    stats["success"] += bool(result.metrics and result.metrics.get("success"))
                bar.update(1)
                bar.set_postfix(SR=f"{100 * stats['success'] / max(1, stats['done']):.0f}%",
                                scene=scene_id[-24:], refresh=False)
                if not why and (why := budget.exceeded()):
                    # No robot starts another episode; the missions in flight see the budget at their
                    # next poll and are cancelled (run_episode).
                    self._stop.set()
        finally:
            self._stop.set()
            bar.close()
        not_run = len(todo) - ran
        why = budget.exceeded() or why  # what was spent once every robot has stopped
        stopped = Budget.reason(why, n_stopped, not_run) if why and (n_stopped or not_run) else ""
        if stopped and self._explorations_stopped:
            stopped += "; " + "; ".join(str(x) for x in self._explorations_stopped)
        spent = budget.spent
        latest = self.log.load()
        results = [latest[str(e.episode_id)] for e in selected if str(e.episode_id) in latest]
        row = summary_row(results, self.label)
        tables = write_tables([row], self.out_dir / SUMMARY_STEM, title=f"Evaluation: {self.label}")
        self._append_skipped(tables[0], results)
        if stopped:
            log.warning("run stopped: %s", stopped)
        with open(tables[0], "a", encoding="utf-8") as f:
            f.write(ledger_markdown([r for r in results if r.status == "done" and r.metrics is not None], stopped,
                                    spent))
        self._write_pictures_and_predictions(selected, results, gt or {}, tables[0])
        return RunReport(self.out_dir, results, row, ran, resumed, time.monotonic() - t0, tables, maps, stopped,
                         spent)

    def _halted(self) -> bool:
        """No episode may start: the run is stopping, or its budget is reached."""
        return bool(self._halt_reason())

    def _halt_reason(self) -> str:
        return self._budget.exceeded() or ("the run was interrupted" if self._stop.is_set() else "")

    def _concurrent(self, groups: dict[str, list[Episode]], gt: dict[str, GroundTruth], maps: dict[str, str]):
        """(scene, result) of every pending episode, one worker thread per robot over its shard of scenes.

        A worker hands each result over and waits until it is logged before it starts the next episode,
        so a stop (the budget) is seen before any robot begins another one; the log is written by the
        caller's thread only."""
        self._stop = threading.Event()
        shards = shard_scenes(groups, len(self.lanes))
        handoff: queue.Queue = queue.Queue()

        def work(lane: Lane, scenes: list[str]) -> None:
            runner = copy.copy(self)  # the same settings, log and map index; this robot's gateway
            runner.gateway, runner.scenes = lane.gateway, lane.scenes
            try:
                for scene_id in scenes:
                    if self._halted():
                        break
                    scene_run = runner._run_scene(scene_id, groups[scene_id], gt, maps)
                    for result in scene_run:
                        logged = threading.Event()
                        handoff.put((scene_id, result, logged))
                        logged.wait()
                        if self._halted():
                            scene_run.close()  # the next episode is never started
                            break
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
                handoff.put((None, exc, None))
            finally:
                handoff.put(None)

        workers = [threading.Thread(target=work, args=(lane, shard), name=f"eval-robot{i}", daemon=True)
                   for i, (lane, shard) in enumerate(zip(self.lanes, shards)) if shard]
        for w in workers:
            w.start()
        running = len(workers)
        try:
            while running:
                item = handoff.get()
                if item is None:
                    running -= 1
                    continue
                scene_id, result, logged = item
                if logged is None:
                    raise result
                try:
                    yield scene_id, result
                finally:
                    logged.set()
        finally:
            self._stop.set()

    @staticmethod
    def _append_skipped(md: Path, results: Sequence[EpisodeResult]) -> None:
        rows = skipped_report(results)
        if not rows:
            return
        lines = ["", f"## Not evaluated ({len(rows)})", "", "| episode | scene | reason |", "|---|---|---|"]
        lines += [f"| {e} | {s} | {r.replace('|', '/')} |" for e, s, r in rows]
        with open(md, "a", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")

    def _write_pictures_and_predictions(self, selected: Sequence[Episode], results: Sequence[EpisodeResult],
                                        gt: dict[str, GroundTruth], md: Path) -> None:
        """The episodes of summary.md, each with its top-down plot in ``plots/`` unless plots are off, and the
        VLN-CE prediction file."""
        import numpy as np

        from evaluation.plots import EpisodeGeometry, plots_markdown, plotted_results, write_episode_plots
        from evaluation.predictions import PREDICTIONS_FILE, write_predictions

        if self.config.plots:
            geometry: dict[str, EpisodeGeometry] = {}
            for e in selected:
                try:
                    ref = self.reference_for(e, gt.get(str(e.episode_id)))
                except ConfigError:
                    ref = None
                geometry[str(e.episode_id)] = EpisodeGeometry(
                    np.asarray(e.start_pose.position_m), np.asarray(e.goal_m), None if ref is None else np.asarray(ref))
            rows = write_episode_plots(results, geometry, self.out_dir)
        else:
            rows = [(r, None) for r in plotted_results(results)]
        path, written, left_out = write_predictions(
            results, self.out_dir / PREDICTIONS_FILE, {str(e.episode_id): e.start_pose.heading_rad for e in selected})
        with open(md, "a", encoding="utf-8") as f:
            f.write(f"\nVLN-CE prediction file: [{PREDICTIONS_FILE}]({PREDICTIONS_FILE}) ({written} episodes"
                    + (f"; {left_out} not run are left out" if left_out else "") + ")\n")
            f.write(plots_markdown(rows, drawn=self.config.plots))
        log.info("%s, predictions in %s", f"{len(rows)} episode plots in {self.out_dir / 'plots'}"
                 if self.config.plots else "plots off", path)

    # --- one scene -----------------------------------------------------------------------------------
    def _base(self, e: Episode, **kw) -> EpisodeResult:
        return EpisodeResult(episode_id=str(e.episode_id), scene_id=e.scene_id, instruction=e.instruction,
                             map_source=self.config.map_source.value, finished_at_s=time.time(), **kw)

    def _run_scene(self, scene_id: str, group: list[Episode], gt: dict[str, GroundTruth], maps: dict[str, str]):
        cfg = self.config
        try:
            spec = group[0].scene_path(cfg.scenes_dir)
        except SceneNotFoundError as exc:
            log.warning("scene %s missing: skipping %d episodes (%s)", scene_id, len(group), exc)
            for e in group:
                yield self._base(e, status="skipped", reason=str(exc))
            return
        if not is_generated_spec(spec):
            # robot-io runs in another process, maybe in another directory: hand it an absolute path.
            spec = str(Path(spec).resolve())
        if self.scenes is not None:
            try:
                summary = self.scenes.load_scene(spec)
                log.info("scene %s loaded (%d floors, %.0f m2 reachable)", spec, summary.floors,
                         summary.reachable_area_m2)
            except Exception as exc:  # noqa: BLE001 - any failure to load is reported per episode
                log.warning("scene %s could not be loaded: %s", spec, exc)
                for e in group:
                    yield self._base(e, status="skipped", reason=f"scene could not be loaded: {exc}")
                return
        try:
            map_id = self.ensure_map(scene_id, spec)
        except ExplorationStopped as exc:
            # Not the scene's failure: its episodes were never started and run on resume.
            log.warning("%s", exc)
            self._explorations_stopped.append(exc)
            return
        except (EvaluationError, MetricsError) as exc:
            log.error("no map for %s: %s", scene_id, exc)
            for e in group:
                yield self._base(e, status="error", reason=f"no map: {exc}")
            return
        maps[scene_id] = map_id
        for e in group:
            if self._halted():  # e.g. the wall-time budget ran out while the map was built
                return
            yield self.run_episode(e, map_id, gt.get(str(e.episode_id)))

    # --- maps ----------------------------------------------------------------------------------------
    def ensure_map(self, scene_id: str, spec: str) -> str:
        """The map of this scene and source: the cached one if the gateway still has it, else a new one."""
        source = self.config.map_source
        cached = self.maps.get(scene_id, source)
        if cached and self.gateway.map_info(cached) is not None:
            log.info("reusing map %s for %s (%s)", cached, scene_id, source.value)
            return cached
        map_id = map_id_for(scene_id, source)
        if source is MapSource.CURATED:
            self._upload_curated(spec, map_id)
        else:
            self._explore(map_id, scene_id)
        self.maps.put(scene_id, source, map_id)
        return map_id

    def _explore(self, map_id: str, scene_id: str = "") -> None:
        """Explore the robot's scene into ``map_id``. When the run stops meanwhile (its budget), the
        exploration is cancelled and :class:`ExplorationStopped` raised; one that does not end in time is
        cancelled too, so that no robot is left exploring for nobody."""
        cfg = self.config
        t0 = time.monotonic()
        try:
            xid = self.gateway.submit_exploration(map_id, max_steps=cfg.exploration_max_steps,
                                                  reconstruction=cfg.reconstruction)
        except GatewayError as exc:
            raise MapUnavailable(f"exploration for {map_id}: {exc}") from None
        try:
            # Each poll looks at the run's budget, as a mission's polls do.
            # Each poll also logs the exploration's standing when it changed (step, frontiers, time
            # left): on a real robot an exploration runs for many minutes.
            shown = [""]

            def poll(rec: dict[str, Any]) -> bool:
                line = f"{rec.get('stage') or ''}: {rec.get('message') or ''}"
                if rec.get("message") and line != shown[0]:
                    log.info("exploring %s: %s", map_id, line)
                    shown[0] = line
                return self._halted()

            rec = self.gateway.wait(self.gateway.exploration, xid, cfg.exploration_timeout_s, cfg.poll_s, until=poll)
        except MissionTimeout as exc:
            self._cancel_exploration(xid)
            raise MapUnavailable(f"exploration for {map_id}: {exc}") from None
        except GatewayError as exc:
            raise MapUnavailable(f"exploration for {map_id}: {exc}") from None
        if rec["state"] not in TERMINAL_STATES:
            why = self._halt_reason()
            rec = self._cancel_exploration(xid)
            if rec["state"] != "succeeded":  # one that stored its map before the cancel reached it is kept
                raise ExplorationStopped(scene_id or map_id, xid, rec["state"], rec.get("stage"), why)
        if rec["state"] != "succeeded":
            raise MapUnavailable(f"exploration {xid} {rec['state']}: {rec.get('error') or rec.get('message') or ''}")
        log.info("explored and reconstructed %s in %.0f s", map_id, time.monotonic() - t0)

    def _cancel_exploration(self, xid: str) -> dict[str, Any]:
        """Cancel a running exploration and wait for its end: the mapper stops it within a step, or
        cancels the map build it waits on."""
        return self._cancel_then_wait("exploration", xid, self.gateway.cancel_exploration, self.gateway.exploration)

    def _cancel_then_wait(self, kind: str, rid: str, cancel, read) -> dict[str, Any]:
        """``cancel(rid)``, then wait (``stop_wait_s``) for the record ``read(rid)`` to end; the record
        as it stands when it does not end. A refused cancel is logged: the wait says the rest."""
        try:
            cancel(rid)
        except GatewayError as exc:
            log.warning("could not cancel %s %s: %s", kind, rid, exc)
        try:
            return self.gateway.wait(read, rid, self.config.stop_wait_s, self.config.poll_s)
        except MissionTimeout as exc:
            log.warning("%s %s did not end after its cancel: %s", kind, rid, exc)
            return read(rid)

    def _upload_curated(self, spec: str, map_id: str) -> None:
        from evaluation.clouds import sample_scene_cloud
        from shared.cloud import encode

        cfg = self.config
        builder = self.scene_builder
        if builder is None:
            from libs.world import load_scene as builder
        try:
            scene = builder(spec, cfg.scenes_dir)
        except Exception as exc:  # noqa: BLE001
            raise MapUnavailable(f"cannot build scene {spec} for its curated cloud: {exc}") from None
        cloud = sample_scene_cloud(scene, density_per_m2=cfg.curated_density_per_m2,
                                   max_points=cfg.curated_max_points, seed=cfg.seed)
        try:
            info = self.gateway.upload_map(map_id, encode(cloud), filename=f"{map_id}.ply")
        except GatewayError as exc:
            raise MapUnavailable(f"upload of the curated cloud {map_id}: {exc}") from None
        log.info("uploaded curated cloud %s: %d points", map_id, info.get("point_count", len(cloud)))

    # --- one episode ---------------------------------------------------------------------------------
    def reference_for(self, e: Episode, gt: GroundTruth | None) -> list[tuple[float, float, float]] | None:
        use_gt = self.config.reference == "gt" or (self.config.reference == "auto" and gt is not None)
        if use_gt:
            if gt is None:
                raise ConfigError(f"episode {e.episode_id} has no ground-truth record")
            pts = gt.locations_m
        else:
            pts = e.reference_path_m
        return [tuple(float(v) for v in p) for p in pts] if len(pts) else None

    def mission_options(self, e: Episode, gt: GroundTruth | None) -> MissionOptions:
        """The mission's options, validated by the shared schema (the planner's contract)."""
        cfg = self.config
        return MissionOptions(
            policy=cfg.policy, policy_config=cfg.policy_config, max_steps=cfg.max_steps,
            anticipation=cfg.anticipation, anticipation_hfov_deg=cfg.anticipation_hfov_deg,
            anticipation_splat_mode=cfg.anticipation_splat_mode, anticipation_views=cfg.anticipation_views,
            spatial_map=cfg.spatial_map, goal_m=tuple(float(v) for v in e.goal_m),
            reference_path_m=self.reference_for(e, gt), start_pose=e.start_pose,
            seed=episode_seed(cfg.seed, e.episode_id), record=True if cfg.record else None)

    def run_episode(self, e: Episode, map_id: str, gt: GroundTruth | None = None) -> EpisodeResult:
        """One mission, start to end; never raises for a failure of the system (it becomes ``error``)."""
        cfg = self.config
        opts = self.mission_options(e, gt)
        brief = {"policy": cfg.policy, "max_steps": cfg.max_steps, "anticipation": cfg.anticipation,
                 "anticipation_hfov_deg": cfg.anticipation_hfov_deg, "spatial_map": cfg.spatial_map,
                 "anticipation_splat_mode": cfg.anticipation_splat_mode, "anticipation_views": cfg.anticipation_views}
        base = {"map_id": map_id, "seed": opts.seed, "options": brief}
        t0 = time.monotonic()
        try:
            mid = self.gateway.submit_mission(e.instruction, map_id, opts.model_dump(mode="json"))
        except GatewayError as exc:
            return self._base(e, status="error", reason=f"mission refused: {exc}", **base)
        why = ""

        def stop_now(rec: dict[str, Any]) -> bool:
            # Each poll tells the budget what this mission has spent so far (other robots' missions count too).
            nonlocal why
            why = self._budget.track(mid, Spent.of(rec)) or ("the run was interrupted" if self._stop.is_set() else "")
            return bool(why)

        try:
            rec = self.gateway.wait(self.gateway.mission, mid, cfg.mission_timeout_s, cfg.poll_s, until=stop_now)
            if rec["state"] not in TERMINAL_STATES:
                rec = self._cancel_and_wait(mid)
        except MissionTimeout as exc:
            # Waited for as a budget's stop is: the next episode's mission must not start while this one still
            # drives the robot (nor a resume find it running).
            try:
                self._cancel_and_wait(mid)
            except GatewayError as cancel_exc:
                log.warning("could not see %s end after its timeout: %s", mid, cancel_exc)
            return self._base(e, status="error", reason=f"timeout: {exc}", mission_id=mid,
                              wall_s=time.monotonic() - t0, **base)
        except GatewayError as exc:
            return self._base(e, status="error", reason=f"lost the mission: {exc}", mission_id=mid,
                              wall_s=time.monotonic() - t0, **base)
        result = self._result(e, mid, rec, time.monotonic() - t0, base)
        if why and result.status != "done":
            # Cancelled (or still ending) because of the budget: not the policy's failure, and run again on
            # resume. A mission that finished before the cancel reached it keeps its result.
            result = result.model_copy(update={"status": "stopped", "metrics": None,
                                               "reason": f"stopped mid-way: {why}"})
        if cfg.record:
            result.recording = self._keep_recording(e, mid)
        return result

    def _cancel_and_wait(self, mid: str) -> dict[str, Any]:
        """Cancel a running mission and wait for its end: the planner ends it between steps, and the
        step in flight is paid and recorded."""
        return self._cancel_then_wait("mission", mid, self.gateway.cancel_mission, self.gateway.mission)

    def _keep_recording(self, e: Episode, mid: str) -> str | None:
        """Copy the mission's .rrd into ``<run>/recordings/`` (a missing one is logged, not an error)."""
        from evaluation.plots import plot_name

        rel = f"recordings/{plot_name(e.episode_id)[:-4]}.rrd"
        try:
            data = self.gateway.recording(mid)
        except GatewayError as exc:
            log.warning("no recording of %s (episode %s): %s", mid, e.episode_id, exc)
            return None
        path = self.out_dir / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        return rel

    def _final_event(self, mid: str, rec: dict[str, Any]) -> MissionFinished | None:
        """The mission's typed end (None when it ended without one: failed, cancelled, reaped)."""
        try:
            events = self.gateway.history(mid, after=max(-1, int(rec.get("last_seq", 0)) - 1), limit=10)
        except GatewayError as exc:
            log.warning("no history for %s: %s", mid, exc)
            return None
        ends = [ev for ev in events if ev.get("kind") in ("finished", "error")]
        if not ends or (ends[-1].get("data") or {}).get("type") != "mission_finished":
            return None
        try:
            return MissionFinished.model_validate(ends[-1]["data"])
        except ValidationError as exc:
            log.warning("mission %s: unreadable final event: %s", mid, exc)
            return None

    def _ledger(self, mid: str) -> list[dict[str, Any]]:
        """The mission's per-step ledger from its step events ([] when the history is unavailable)."""
        try:
            events = self.gateway.history(mid, after=-1, limit=min(1000, 2 * self.config.max_steps + 10))
        except GatewayError as exc:
            log.warning("no step ledger for %s: %s", mid, exc)
            return []
        return step_ledger(events)

    def _result(self, e: Episode, mid: str, rec: dict[str, Any], wall_s: float, base: dict) -> EpisodeResult:
        end = self._final_event(mid, rec)
        steps = self._ledger(mid)
        # The record's running totals stand in when the mission never sent its end (e.g. it failed).
        usage = end.usage if end is not None else UsageData(
            prompt_tokens=int(rec.get("prompt_tokens", 0)), completion_tokens=int(rec.get("completion_tokens", 0)),
            cost_usd=float(rec.get("cost_usd", 0.0)))
        common = dict(
            mission_id=mid, state=rec["state"], wall_s=round(wall_s, 3),
            trajectory_m=[list(p) for p in end.trajectory_m] if end is not None else rec.get("trajectory") or [],
            decisions=rec.get("decisions") or [],
            step_latency_s=list(end.step_latency_s) if end is not None else [],
            prompt_tokens=usage.prompt_tokens, completion_tokens=usage.completion_tokens, cost_usd=usage.cost_usd,
            ledger=steps, stage_s=stage_totals(steps), **base)
        if rec["state"] == "cancelled":
            return self._base(e, status="error", reason="the mission was cancelled", **common)
        if end is None or end.metrics is None:
            why = rec.get("error") or (end.error or end.reason if end is not None else "") \
                or "the mission ended without metrics"
            return self._base(e, status="error", reason=str(why), **common)
        try:
            metrics = metrics_from_dict(end.metrics.model_dump()).to_dict()
        except MetricsError as exc:
            return self._base(e, status="error", reason=f"bad metrics from the planner: {exc}", **common)
        # A failed mission with metrics ran out of steps: a VLN-CE failure, not a system error.
        return self._base(e, status="done", reason=end.reason or end.error, metrics=metrics, **common)


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, *a, **kw) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="ep", dynamic_ncols=True, smoothing=0.1)
