"""Scripted planner, mapper and reconstructor for the gateway's tests, bench and dashboard demos.

Like dora's ``MockNode``: small fake services that speak the real contracts (:mod:`shared.keys`,
:mod:`shared.schemas`) on any bus (FakeBus or zenoh), accept a job and publish a few realistic
events with small JPEG pictures (panorama, spatial map, each candidate's observed and anticipated view).
"""

from __future__ import annotations

import functools
import io
import math
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from shared import keys
from shared.bus.base import Closeable
from shared.bus.typed import NotFound, TypedBus
from shared.schemas import (
    CancelRequest, Candidate, CandidateKind, Decision, EpisodeMetricsData, ExplorationFinished, ExplorationProgress,
    ExplorationCancelRequest, ExplorationRequest, ExplorationStarted, GeodesicReply, GeodesicRequest, JobCancelled,
    LoadSceneRequest, MapChunk, MapChunkRequest, SceneGraph, SceneGraphRequest,
    MapImportRequest, MapInfo, MapListReply, MapRequest, JobAccepted, JobEvent, JobEventKind,
    MissionFinished, MissionRequest, MissionStarted, JobState, MissionStep, Ping, Pose, RoomInfo, SceneSummary,
)

_PALETTE = np.array([[66, 135, 245], [245, 166, 35], [80, 200, 120], [220, 80, 90], [160, 110, 220],
                     [70, 200, 200]], np.uint8)


def jpeg(rgb: np.ndarray, quality: int = 80) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def room_view(seed: int, size: int = 128, label: str = "", hole: bool = False) -> np.ndarray:
    """A plausible indoor view: floor and wall gradient, a coloured 'object', optional render holes."""
    rng = np.random.default_rng(seed)
    h = w = size
    y = np.linspace(0, 1, h)[:, None, None]
    wall = np.array([200, 190, 175]) * (0.75 + 0.25 * (1 - y))
    floor = np.array([140, 110, 80]) * (0.6 + 0.4 * y)
    img = np.where(y > 0.62, floor, wall) * np.ones((1, w, 1))
    c = _PALETTE[rng.integers(len(_PALETTE))]
    x0, bw = rng.integers(5, w // 2), rng.integers(w // 6, w // 3)
    img[int(h * 0.35):int(h * 0.7), x0:x0 + bw] = c
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    if hole:
        holes = rng.random((h // 8, w // 8)) < 0.15
        img[np.kron(holes, np.ones((8, 8), bool))] = 0
    if label:
        cv2.putText(img, label, (4, h - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    return img


@functools.lru_cache(maxsize=4096)
def view_jpeg(seed: int, size: int, label: str = "", hole: bool = False) -> bytes:
    """:func:`room_view` as JPEG, memoised: a bench's scripted planner must not eat the CPU it measures."""
    return jpeg(room_view(seed, size, label, hole))


def spatial_map(trajectory: list[tuple[float, float]], candidates: list[tuple[float, float]],
                size: int = 256, extent_m: float = 12.0) -> np.ndarray:
    img = np.full((size, size, 3), 235, np.uint8)
    s = size / extent_m

    def px(p):
        return int(size / 2 + p[0] * s), int(size / 2 - p[1] * s)

    cv2.rectangle(img, px((-5, -5)), px((5, 5)), (60, 60, 60), 2)
    cv2.line(img, px((0, -5)), px((0, 1)), (60, 60, 60), 2)
    for a, b in zip(trajectory, trajectory[1:]):
        cv2.line(img, px(a), px(b), (30, 120, 220), 2, cv2.LINE_AA)
    for c in candidates:
        cv2.circle(img, px(c), 4, (240, 150, 20), -1, cv2.LINE_AA)
    if trajectory:
        cv2.circle(img, px(trajectory[-1]), 6, (220, 40, 40), -1, cv2.LINE_AA)
    return img


@dataclass
class _Run:
    request: MissionRequest
    cancel: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None


class ScriptedPlanner:
    """Serves MISSION_SUBMIT/MISSION_CANCEL; each mission walks ``steps`` steps on a thread.

    Refuses instructions containing ``"refuse"`` (accepted=False) and map ids starting ``"broken"``
    (BAD_REQUEST), so tests can exercise every answer.
    """

    def __init__(self, bus: TypedBus, robot: str = "robot0", *, steps: int = 3, step_interval_s: float = 0.01,
                 candidates: int = 3, image_px: int = 96, image_variants: int | None = None):
        self.bus, self.robot = bus, robot
        # image_variants: reuse that many distinct pictures per slot (cheap events for benchmarks).
        self.image_variants = image_variants
        self.steps, self.step_interval_s, self.n_candidates, self.image_px = steps, step_interval_s, candidates, image_px
        self.runs: dict[str, _Run] = {}
        # Where a test sets one: a mission holds its finish until the event is set (bounded, 10 s), so it is
        # still running for as long as the test needs, without a step interval that load could outrun.
        self.finish_gate: threading.Event | None = None
        self._entities: list[Closeable] = [
            bus.serve(keys.MISSION_SUBMIT.format(robot=robot), MissionRequest, self._submit, workers=2),
            bus.serve(keys.MISSION_CANCEL.format(robot=robot), CancelRequest, self._cancel),
        ]

    def _submit(self, req: MissionRequest) -> JobAccepted:
        if "refuse" in req.instruction:
            return JobAccepted(job_id=req.mission_id, accepted=False, reason="scripted refusal")
        if req.map_id.startswith("broken"):
            raise ValueError(f"map {req.map_id!r} cannot be navigated")
        run = _Run(req)
        run.thread = threading.Thread(target=self._walk, args=(run,), daemon=True, name=f"walk-{req.mission_id}")
        self.runs[req.mission_id] = run
        run.thread.start()
        return JobAccepted(job_id=req.mission_id, accepted=True)

    def _cancel(self, req: CancelRequest) -> JobAccepted:
        run = self.runs.get(req.mission_id)
        if run is None:
            raise NotFound(f"no mission {req.mission_id!r}")
        run.cancel.set()
        return JobAccepted(job_id=req.mission_id, accepted=True)

    def _walk(self, run: _Run) -> None:
        req, mid = run.request, run.request.mission_id
        key = keys.MISSION_EVENTS.format(robot=self.robot, mission=mid)
        seq = 0

        def emit(kind, state, step, data, images=None):
            nonlocal seq
            self.bus.publish(key, JobEvent(job_id=mid, seq=seq, kind=kind, state=state, step=step,
                                               data=data, images=images or {}))
            seq += 1

        pos, heading = np.zeros(3), 0.0
        traj = [(0.0, 0.0)]
        emit(JobEventKind.STARTED, JobState.RUNNING, 0,
             MissionStarted(pose=Pose(position_m=tuple(pos.tolist()), heading_rad=heading),
                            instruction=req.instruction, map_id=req.map_id, options=req.options))
        steps = min(self.steps, req.options.max_steps)
        for step in range(1, steps + 1):
            if run.cancel.wait(self.step_interval_s):
                emit(JobEventKind.FINISHED, JobState.CANCELLED, step - 1, JobCancelled(message="cancelled"))
                return
            n = self.n_candidates
            cands = [Candidate(index=i, dx_m=float(1.5 * math.cos(heading + (i - n // 2) * 0.7)),
                               dy_m=float(1.5 * math.sin(heading + (i - n // 2) * 0.7)),
                               angle_rad=(i - n // 2) * 0.7, distance_m=1.5, score=1.0 / (1 + i)) for i in range(n)]
            cands.append(Candidate(index=n, kind=CandidateKind.STOP))
            final = step == steps
            choice = cands[-1] if final else cands[step % n]
            decision = Decision(candidate_index=choice.index, kind=choice.kind, backend="scripted",
                                reasoning=(f"Step {step}: the instruction mentions the kitchen; candidate "
                                           f"{choice.index}'s anticipated view shows a doorway towards it."
                                           if not final else "The goal room is in view: stop."),
                                prompt_tokens=800 + 10 * step, completion_tokens=60, cost_usd=0.001)
            px = self.image_px
            images = self._images(step, px, n, traj, pos, cands)
            if not final:
                pos = pos + np.array([choice.dx_m, choice.dy_m, 0.0])
                heading = math.atan2(choice.dy_m, choice.dx_m)
                traj.append((float(pos[0]), float(pos[1])))
            emit(JobEventKind.STEP, JobState.RUNNING, step,
                 MissionStep(pose=Pose(position_m=tuple(pos.tolist()), heading_rad=heading), candidates=cands,
                             decision=decision, timings_s={"observe": 0.05, "render": 0.12, "policy": 0.3}), images)
        metrics = None
        if req.options.goal_m is not None:
            ne = float(np.linalg.norm(pos - np.asarray(req.options.goal_m)))
            ok = ne <= 3.0
            metrics = EpisodeMetricsData(ne_m=ne, success=ok, oracle_success=ok, oracle_ne_m=ne, tl_m=1.5 * (steps - 1),
                                         spl=0.8 * ok, ndtw=0.7, sdtw=0.7 * ok, shortest_m=1.5 * (steps - 1),
                                         stop_called=True, steps=steps, goal_reachable=True)
        traj_m = [(x, y, 0.0) for x, y in traj]
        if self.finish_gate is not None:
            self.finish_gate.wait(10.0)
        emit(JobEventKind.FINISHED, JobState.SUCCEEDED, steps,
             MissionFinished(stop_called=True, steps=steps, trajectory_m=traj_m, metrics=metrics))

    def _images(self, step: int, px: int, n: int, traj, pos, cands) -> dict[str, bytes]:
        if self.image_variants:
            k = step % self.image_variants
            images = {"panorama": view_jpeg(100_000 + k, px * 3), "map": view_jpeg(200_000 + k, px * 2)}
            for c in cands[:n]:
                images[f"cand_{c.index}_observed"] = view_jpeg(1000 * k + c.index, px, "observed")
                images[f"cand_{c.index}_anticipated"] = view_jpeg(1000 * k + c.index, px, "anticipated", True)
            return images
        images = {"panorama": jpeg(np.concatenate([room_view(100 * step + v, px // 2) for v in range(12)], 1)),
                  "map": jpeg(spatial_map(traj, [(pos[0] + c.dx_m, pos[1] + c.dy_m) for c in cands[:n]]))}
        for c in cands[:n]:
            images[f"cand_{c.index}_observed"] = jpeg(room_view(1000 * step + c.index, px, "observed"))
            images[f"cand_{c.index}_anticipated"] = jpeg(room_view(1000 * step + c.index, px, "anticipated",
                                                                   hole=True))
        return images

    def close(self) -> None:
        for run in self.runs.values():
            run.cancel.set()
        for e in self._entities:
            e.close()
        for run in self.runs.values():
            if run.thread is not None:
                run.thread.join(5.0)


class ScriptedMapper:
    """Serves MAPPER_EXPLORE and EXPLORATION_CANCEL; an exploration publishes progress events and finishes
    with its map. A map id containing ``"hang"`` (or every exploration, with ``hold`` set) holds at its
    last stage ("reconstructing") until the exploration is cancelled (or 60 s), so a test can cancel it
    mid-way without racing its end. A
    cancelled exploration ends ``cancelled`` with its stage and adds no map. ``cancels`` counts the
    accepted cancels."""

    def __init__(self, bus: TypedBus, robot: str = "robot0", *, stages: int = 3, stage_interval_s: float = 0.01,
                 reconstructor: ScriptedReconstructor | None = None):
        self.bus, self.robot, self.stages, self.interval_s = bus, robot, stages, stage_interval_s
        self.reconstructor = reconstructor
        self.cancels = 0
        self.hold = False
        self._cancel: dict[str, threading.Event] = {}
        self._threads: list[threading.Thread] = []
        self._entities = [bus.serve(keys.MAPPER_EXPLORE.format(robot=robot), ExplorationRequest, self._submit),
                          bus.serve(keys.EXPLORATION_CANCEL.format(robot=robot), ExplorationCancelRequest,
                                    self._cancel_req)]

    def _submit(self, req: ExplorationRequest) -> JobAccepted:
        self._cancel[req.exploration_id] = threading.Event()
        t = threading.Thread(target=self._run, args=(req,), daemon=True)
        self._threads.append(t)
        t.start()
        return JobAccepted(job_id=req.exploration_id, accepted=True)

    def _cancel_req(self, req: ExplorationCancelRequest) -> JobAccepted:
        ev = self._cancel.get(req.exploration_id)
        if ev is None or ev.is_set():
            return JobAccepted(job_id=req.exploration_id, accepted=False, reason="no such exploration here")
        ev.set()
        self.cancels += 1
        return JobAccepted(job_id=req.exploration_id, accepted=True)

    def _run(self, req: ExplorationRequest) -> None:
        key = keys.EXPLORATION_EVENTS.format(robot=self.robot, exploration=req.exploration_id)
        cancel = self._cancel[req.exploration_id]
        names = ["exploring", "touring", "reconstructing"]
        self.bus.publish(key, JobEvent(job_id=req.exploration_id, seq=0, kind=JobEventKind.STARTED,
                                           state=JobState.RUNNING, data=ExplorationStarted(map_id=req.map_id)))
        stage, sent = None, 0
        for i in range(1, self.stages + 1):
            if cancel.wait(self.interval_s) if self.interval_s else cancel.is_set():
                break
            stage = names[min(i, len(names)) - 1]
            self.bus.publish(key, JobEvent(job_id=req.exploration_id, seq=i, kind=JobEventKind.PROGRESS, state=JobState.RUNNING,
                step=i * 10, data=ExplorationProgress(stage=stage, progress=i / (self.stages + 1)),
                images={"map": jpeg(spatial_map([(0, 0), (i, 0)], []))}))
            sent = i
            # The hold comes after the last stage's event: a test sees it running in that stage first.
            if i == self.stages and (self.hold or "hang" in req.map_id) and cancel.wait(60.0):
                break
        if cancel.is_set():
            self.bus.publish(key, JobEvent(job_id=req.exploration_id, seq=sent + 1, kind=JobEventKind.FINISHED,
                                           state=JobState.CANCELLED, step=sent * 10,
                                           data=JobCancelled(message=f"cancelled on request while {stage}",
                                                             stage=stage)))
            return
        if self.reconstructor is not None:
            self.reconstructor.add_random(req.map_id, 2000)
        self.bus.publish(key, JobEvent(job_id=req.exploration_id, seq=self.stages + 1,
                                           kind=JobEventKind.FINISHED, state=JobState.SUCCEEDED,
                                           step=self.stages * 10, data=ExplorationFinished(map_id=req.map_id, version=1, points=2000,
                                                                                  regions=self.stages)))

    def close(self) -> None:
        for ev in self._cancel.values():
            ev.set()
        for e in self._entities:
            e.close()
        for t in self._threads:
            t.join(5.0)


class ScriptedGround:
    """Serves IO_GEODESIC over a flat square of walkable ground (``[0, size_m]^2`` at z = 0): straight-line
    distances, and how far each end lies off that ground - what the gateway checks poses against."""

    def __init__(self, bus: TypedBus, robot: str = "robot0", *, size_m: float = 12.0):
        self.size_m = size_m
        self._entity = bus.serve(keys.IO_GEODESIC.format(robot=robot), GeodesicRequest, self._geodesic)

    def off_m(self, p) -> float:
        p = np.asarray(p, np.float64)
        q = np.array([min(max(p[0], 0.0), self.size_m), min(max(p[1], 0.0), self.size_m), 0.0])
        return float(np.linalg.norm(p - q))

    def _geodesic(self, req: GeodesicRequest) -> GeodesicReply:
        d = float(np.linalg.norm(np.subtract(req.goal_m, req.start_m)))
        return GeodesicReply(distance_m=d, start_off_m=self.off_m(req.start_m), goal_off_m=self.off_m(req.goal_m))

    def close(self) -> None:
        self._entity.close()


class ScriptedRobotIo:
    """Serves IO_SCENE and IO_LOAD_SCENE like a simulator robot-io.

    Specs ``generated:<seed>[:floors=N]`` load (once ``load_gate`` is set, where one is given: a slow load
    that lasts exactly as long as the test needs); anything else is refused as a bad request, as robot-io
    refuses a mesh it cannot read. ``loaded`` lists the loads in order.
    """

    def __init__(self, bus: TypedBus, robot: str = "robot0", *, scene: str = "generated:0",
                 load_gate: threading.Event | None = None):
        self.load_gate = load_gate
        self.loaded: list[str] = []
        self._summary = self._summarise(scene)
        self._lock = threading.Lock()
        self._entities = [
            bus.serve(keys.IO_SCENE.format(robot=robot), Ping, lambda _p: self._summary),
            bus.serve(keys.IO_LOAD_SCENE.format(robot=robot), LoadSceneRequest, self._load),
        ]

    @staticmethod
    def _summarise(spec: str) -> SceneSummary:
        parts = spec.split(":")
        if len(parts) < 2 or parts[0] != "generated" or not parts[1].isdigit():
            raise ValueError(f"{spec!r}: not a scene this robot can load (generated:<seed>[:floors=N])")
        floors = 1
        for opt in parts[2:]:
            name, _, value = opt.partition("=")
            if name != "floors" or value not in ("1", "2"):
                raise ValueError(f"{spec!r}: unknown option {opt!r}")
            floors = int(value)
        seed = int(parts[1])
        size = 8.0 + seed % 5
        rooms = [RoomInfo(name=f"room{i}", room_type=t, floor=0, bounds_min_m=(i * size / 3, 0.0, 0.0),
                          bounds_max_m=((i + 1) * size / 3, size, 2.6))
                 for i, t in enumerate(("kitchen", "living room", "bedroom"))]
        return SceneSummary(scene=spec, bounds_min_m=(0.0, 0.0, 0.0), bounds_max_m=(size, size, 2.6 * floors),
                            floors=floors, reachable_area_m2=0.7 * size * size * floors,
                            label_names={0: "floor", 1: "wall"}, rooms=rooms,
                            start_pose=Pose(position_m=(size / 2, size / 2, 0.0)))

    def _load(self, req: LoadSceneRequest) -> SceneSummary:
        summary = self._summarise(req.scene)  # a bad spec fails before anything changes
        with self._lock:
            # Bounded, so that a gateway which waits on this load instead of refusing fails in seconds, not hangs.
            if self.load_gate is not None and not self.load_gate.wait(10.0):
                raise TimeoutError("the test never let the scene load finish")
            self._summary = summary
            self.loaded.append(req.scene)
        return summary

    def close(self) -> None:
        for e in self._entities:
            e.close()


class ScriptedReconstructor:
    """An in-memory map store behind MAP_LIST/INFO/CHUNK/IMPORT (imports parse PLY/PCD with open3d)."""

    def __init__(self, bus: TypedBus):
        self.maps: dict[str, tuple[MapInfo, np.ndarray, np.ndarray, np.ndarray | None]] = {}
        self.view_dirs: dict[str, np.ndarray | None] = {}  # PointCloud.view_dirs per map
        self._lock = threading.Lock()
        self._entities = [
            bus.serve(keys.MAP_LIST.format(), Ping, self._list),
            bus.serve(keys.MAP_INFO.pattern(), MapRequest, self._info, workers=2),
            bus.serve(keys.MAP_CHUNK.pattern(), MapChunkRequest, self._chunk, workers=2),
            bus.serve(keys.MAP_IMPORT.pattern(), MapImportRequest, self._import),
            bus.serve(keys.MAP_SCENE_GRAPH.pattern(), SceneGraphRequest, self._scene_graph, workers=2),
        ]

    def add(self, map_id: str, xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None = None,
            source: str = "scripted", view_dirs: np.ndarray | None = None,
            label_names: dict[int, str] | None = None) -> MapInfo:
        with self._lock:
            version = self.maps[map_id][0].version + 1 if map_id in self.maps else 1
            info = MapInfo(map_id=map_id, version=version, point_count=len(xyz),
                           bounds_min_m=tuple(map(float, xyz.min(0))) if len(xyz) else (0.0, 0.0, 0.0),
                           bounds_max_m=tuple(map(float, xyz.max(0))) if len(xyz) else (0.0, 0.0, 0.0),
                           source=source, has_labels=labels is not None,
                           label_names=(label_names or {0: "floor", 1: "wall"}) if labels is not None else {})
            self.maps[map_id] = (info, xyz.astype(np.float32), rgb.astype(np.uint8), labels)
            self.view_dirs[map_id] = view_dirs
        return info

    def add_random(self, map_id: str, n: int, seed: int = 0, labels: bool = False) -> MapInfo:
        rng = np.random.default_rng(seed)
        xyz = rng.uniform([-5, -5, 0], [5, 5, 2.5], (n, 3))
        rgb = rng.integers(0, 256, (n, 3))
        return self.add(map_id, xyz, rgb, rng.integers(0, 2, n).astype(np.int32) if labels else None)

    def _get(self, map_id: str):
        entry = self.maps.get(map_id)
        if entry is None:
            raise NotFound(f"no map {map_id!r}")
        return entry

    def _list(self, _: Ping) -> MapListReply:
        return MapListReply(maps=[e[0] for e in self.maps.values()])

    def _info(self, req: MapRequest) -> MapInfo:
        return self._get(req.map_id)[0]

    def _scene_graph(self, req: SceneGraphRequest) -> SceneGraph:
        # The real builder on the stored points, as the reconstructor's store builds it.
        from libs.scenegraph import build_scene_graph
        from shared.cloud import PointCloud

        info, xyz, rgb, labels = self._get(req.map_id)
        cloud = PointCloud(xyz, rgb, labels, dict(info.label_names) if labels is not None else {})
        return build_scene_graph(cloud, map_id=req.map_id, version=info.version)

    def _chunk(self, req: MapChunkRequest) -> MapChunk:
        info, xyz, rgb, labels = self._get(req.map_id)
        count = max(1, math.ceil(len(xyz) / req.max_points))
        if req.index >= count:
            raise ValueError(f"chunk {req.index} >= count {count}")
        sl = slice(req.index * req.max_points, (req.index + 1) * req.max_points)
        views = self.view_dirs.get(req.map_id)
        return MapChunk(map_id=req.map_id, version=info.version, index=req.index, count=count, xyz_m=xyz[sl],
                        rgb=rgb[sl], labels=None if labels is None else labels[sl],
                        view_dirs=None if views is None else views[sl])

    def _import(self, req: MapImportRequest) -> MapInfo:
        import tempfile

        from shared.o3d import o3d

        suffix = "." + req.filename.rsplit(".", 1)[-1]
        with tempfile.NamedTemporaryFile(suffix=suffix) as f:
            f.write(req.data)
            f.flush()
            pcd = o3d.io.read_point_cloud(f.name)
        xyz = np.asarray(pcd.points)
        if len(xyz) == 0:
            raise ValueError(f"{req.filename}: no points could be read")
        rgb = (np.asarray(pcd.colors) * 255).round() if pcd.has_colors() else np.full((len(xyz), 3), 128)
        return self.add(req.map_id, xyz, rgb, source=f"upload:{req.filename}")

    def close(self) -> None:
        for e in self._entities:
            e.close()


def ply_bytes(xyz: np.ndarray, rgb: np.ndarray) -> bytes:
    """A binary PLY of ``xyz`` and ``rgb`` (for upload tests)."""
    buf = io.BytesIO()
    buf.write((f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\nproperty float x\n"
               "property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
               "property uchar blue\nend_header\n").encode())
    rec = np.empty(len(xyz), [("p", "<f4", 3), ("c", "u1", 3)])
    rec["p"], rec["c"] = xyz, rgb
    buf.write(rec.tobytes())
    return buf.getvalue()
