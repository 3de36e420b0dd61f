"""Typed clients for each service's queryables: what one service calls on another.

A client is a thin veneer over :class:`~shared.bus.typed.TypedBus` and :mod:`shared.keys`; it
gives the cores plain method calls (``robot.observe()``, ``renderer.views(...)``) so that they can
be driven by a remote service exactly as by an in-process object in unit tests.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import BinaryIO

import numpy as np

from shared import keys
from shared.bus.typed import RemoteError, TypedBus
from shared.jobs import JobFailedError, await_job
from shared.schemas import (
    BuildCancelRequest, BuildMapRequest, CameraIntrinsics, CancelRequest, Candidate, CandidateSet,
    ExplorationCancelRequest, ExplorationRequest, Frame,
    IMPORT_PART_BYTES, IMPORT_PART_MAX_BYTES,
    GeodesicReply, GeodesicRequest, JobAccepted, JobEvent, LoadSceneRequest, MapBuildFinished, MapImportProgress,
    MapImportRequest, MissionRequest,
    MapChunk, MapChunkRequest, SceneGraph, SceneGraphRequest, MapInfo, MapListReply, MapRequest, MoveRequest, MoveResult, ObserveRequest,
    Panorama, Ping, Pose, PoseReply, RecordReply, RecordRequest, RenderRequest, RenderResult, ResetRequest,
    SceneSummary, SceneViewsRequest, ServiceInfo, ServiceMetrics, SpatialMapRequest, SpatialMapResult, SplatMode,
    TurnRequest, ViewPose,
)

_recording_ids = itertools.count()


class RobotClient:
    """The robot port over the bus (what robot-io serves). Satisfies the mapper's robot protocols."""

    def __init__(self, bus: TypedBus, robot: str, *, timeout_s: float = 30.0,
                 observe_camera: CameraIntrinsics | None = None, recording_px: int | None = 128,
                 recording_prefix: str | None = None):
        self.bus, self.robot, self.timeout_s = bus, robot, timeout_s
        self.observe_camera = observe_camera
        # Tours recorded through this client: frame width, and names "<prefix>-r<k>" (k counts up), so a
        # job's recordings can be told apart on the frames key.
        self.recording_px = recording_px
        self.recording_prefix = recording_prefix
        self._recordings = itertools.count()
        self._pose: Pose | None = None
        self.last_recording: RecordReply | None = None

    def _k(self, key: keys.Key) -> str:
        return key.format(robot=self.robot)

    @property
    def pose(self) -> Pose:
        if self._pose is None:
            self._pose = self.observe().pose
        return self._pose

    def observe(self, camera: CameraIntrinsics | None = None, with_semantic: bool = True) -> Panorama:
        pano = self.bus.request(self._k(keys.IO_OBSERVE),
                                ObserveRequest(camera=camera or self.observe_camera, with_semantic=with_semantic),
                                Panorama, timeout_s=self.timeout_s)
        self._pose = pano.pose
        return pano

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult:
        res = self.bus.request(self._k(keys.IO_MOVE), MoveRequest(dx_m=dx_m, dy_m=dy_m), MoveResult,
                               timeout_s=self.timeout_s)
        self._pose = res.pose
        return res

    def turn(self, angle_rad: float) -> Pose:
        self._pose = self.bus.request(self._k(keys.IO_TURN), TurnRequest(angle_rad=angle_rad), PoseReply,
                                      timeout_s=self.timeout_s).pose
        return self._pose

    def look_around(self) -> list[Frame]:
        # The sweep's frames travel on the recording's frames key, not in this reply.
        self._pose = self.bus.request(self._k(keys.IO_LOOK), Ping(), PoseReply, timeout_s=self.timeout_s).pose
        return []

    def reset(self, pose: Pose | None = None) -> Pose:
        self._pose = self.bus.request(self._k(keys.IO_RESET), ResetRequest(pose=pose), PoseReply,
                                      timeout_s=self.timeout_s).pose
        return self._pose

    def scene(self) -> SceneSummary:
        return self.bus.request(self._k(keys.IO_SCENE), Ping(), SceneSummary, timeout_s=self.timeout_s)

    def load_scene(self, scene: str, timeout_s: float | None = None) -> SceneSummary:
        """Switch the simulator's scene; loading a large mesh takes long (default: at least 120 s)."""
        self._pose = None
        return self.bus.request(self._k(keys.IO_LOAD_SCENE), LoadSceneRequest(scene=scene), SceneSummary,
                                timeout_s=timeout_s or max(self.timeout_s, 120.0))

    def geodesic(self, start_m, goal_m) -> GeodesicReply:
        return self.bus.request(self._k(keys.IO_GEODESIC),
                                GeodesicRequest(start_m=tuple(map(float, start_m)), goal_m=tuple(map(float, goal_m))),
                                GeodesicReply, timeout_s=self.timeout_s)

    def scene_views(self, views: list[ViewPose], camera: CameraIntrinsics | None = None,
                    with_semantic: bool = True) -> RenderResult:
        """Views ray-cast from the simulator's true scene at ``views`` (simulator only)."""
        req = SceneViewsRequest(views=views, camera=camera or CameraIntrinsics(), with_semantic=with_semantic)
        return self.bus.request(self._k(keys.IO_VIEWS), req, RenderResult, timeout_s=self.timeout_s)

    def geodesic_distance(self, start_m, goal_m) -> float:
        d = self.geodesic(start_m, goal_m).distance_m
        return float("inf") if d is None else d

    @contextlib.contextmanager
    def recording(self, sink=None, rate_hz: float = 5.0, *, recording: str | None = None) -> Iterator[str]:
        """Record a tour on robot-io; frames go to whoever subscribes to ``IO_FRAMES`` (the
        reconstructor), not to ``sink``. ``last_recording`` holds the frame count afterwards."""
        if recording is None:
            k = next(self._recordings)
            recording = (f"{self.recording_prefix}-r{k}" if self.recording_prefix
                         else f"rec-{os.getpid()}-{next(_recording_ids)}")
        name = recording
        self.bus.request(self._k(keys.IO_RECORD),
                         RecordRequest(recording=name, start=True, rate_hz=rate_hz, max_width_px=self.recording_px),
                         RecordReply, timeout_s=self.timeout_s)
        try:
            yield name
        finally:
            self.last_recording = self.bus.request(self._k(keys.IO_RECORD),
                                                   RecordRequest(recording=name, start=False), RecordReply,
                                                   timeout_s=self.timeout_s)


class ServicesClient:
    """Every service instance's plumbing: who is alive, their info and their metrics."""

    def __init__(self, bus: TypedBus, *, timeout_s: float = 1.0):
        self.bus, self.timeout_s = bus, timeout_s

    def alive(self, service: str | None = None) -> list[tuple[str, str]]:
        """(service, instance) of every liveliness token up (of one service when given)."""
        pattern = keys.ALIVE.pattern(service=service) if service else keys.ALIVE.pattern()
        out = []
        for token in self.bus.raw.alive(pattern, timeout_s=self.timeout_s):
            parts = keys.ALIVE.parse(token)
            if parts is not None:
                out.append((parts["service"], parts["instance"]))
        return out

    def infos(self, service: str | None = None) -> list[ServiceInfo]:
        """The info of every instance that answered (of one service when given)."""
        pattern = keys.INFO.pattern(service=service) if service else keys.INFO.pattern()
        return [r for r in self.bus.request_all(pattern, Ping(), ServiceInfo, timeout_s=self.timeout_s)
                if not isinstance(r, RemoteError) and (service is None or r.service == service)]

    def metrics(self) -> tuple[list[ServiceMetrics], int]:
        """Every instance's metrics, and how many instances answered with an error instead."""
        answers = self.bus.request_all(keys.METRICS.pattern(), Ping(), ServiceMetrics, timeout_s=self.timeout_s)
        good = [a for a in answers if not isinstance(a, RemoteError)]
        return good, len(answers) - len(good)


class MapperClient:
    def __init__(self, bus: TypedBus, robot: str, *, timeout_s: float = 10.0):
        self.bus, self.robot, self.timeout_s = bus, robot, timeout_s

    def predict(self, pano: Panorama) -> list[Candidate]:
        # The predictor reads depth only; the semantic array (int32, the largest of the panorama's arrays)
        # would cross the bus at every step for nothing.
        pano = pano.model_copy(update={"semantic": None})
        return self.bus.request(keys.MAPPER_PREDICT.format(robot=self.robot), pano, CandidateSet,
                                timeout_s=self.timeout_s).candidates

    def explore(self, req: ExplorationRequest) -> JobAccepted:
        """Submit an exploration job; its events follow on ``EXPLORATION_EVENTS``."""
        return self.bus.request(keys.MAPPER_EXPLORE.format(robot=self.robot), req, JobAccepted,
                                timeout_s=self.timeout_s)

    def cancel_everywhere(self, exploration_id: str) -> list[JobAccepted | RemoteError]:
        """Ask every mapper replica to cancel the exploration (the one zenoh would pick need not run it)."""
        return self.bus.request_all(keys.EXPLORATION_CANCEL.format(robot=self.robot),
                                    ExplorationCancelRequest(exploration_id=exploration_id), JobAccepted,
                                    timeout_s=self.timeout_s)


class PlannerClient:
    """The planner's missions of one robot."""

    def __init__(self, bus: TypedBus, robot: str, *, timeout_s: float = 10.0):
        self.bus, self.robot, self.timeout_s = bus, robot, timeout_s

    def submit(self, req: MissionRequest) -> JobAccepted:
        """Submit a mission job; its events follow on ``MISSION_EVENTS``."""
        return self.bus.request(keys.MISSION_SUBMIT.format(robot=self.robot), req, JobAccepted,
                                timeout_s=self.timeout_s)

    def cancel_everywhere(self, mission_id: str) -> list[JobAccepted | RemoteError]:
        """Ask every planner replica to cancel (the one zenoh would pick need not run the mission)."""
        return self.bus.request_all(keys.MISSION_CANCEL.format(robot=self.robot), CancelRequest(mission_id=mission_id),
                                    JobAccepted, timeout_s=self.timeout_s)


class MapClient:
    """The map store (served by the reconstructor)."""

    def __init__(self, bus: TypedBus, *, timeout_s: float = 30.0, build_stall_s: float = 300.0):
        self.bus, self.timeout_s, self.build_stall_s = bus, timeout_s, build_stall_s

    def list(self) -> list[MapInfo]:
        return self.bus.request(keys.MAP_LIST.format(), Ping(), MapListReply, timeout_s=self.timeout_s).maps

    def info(self, map_id: str, version: int | None = None) -> MapInfo:
        return self.bus.request(keys.MAP_INFO.format(map=map_id), MapRequest(map_id=map_id, version=version),
                                MapInfo, timeout_s=self.timeout_s)

    def scene_graph(self, map_id: str, version: int | None = None) -> SceneGraph:
        """The map version's scene graph (issue 32)."""
        return self.bus.request(keys.MAP_SCENE_GRAPH.format(map=map_id),
                                SceneGraphRequest(map_id=map_id, version=version), SceneGraph, timeout_s=self.timeout_s)

    def import_cloud(self, map_id: str, filename: str, body: bytes | BinaryIO, *,
                     part_bytes: int = IMPORT_PART_BYTES, timeout_s: float | None = None) -> MapInfo:
        """Store a PLY/PCD (bytes, or a binary file read from where it stands) as a new map version.

        It travels in parts of ``part_bytes`` (``MapImportRequest.upload_id``), so neither side holds
        more than a part or two of it; the reconstructor assembles the file on disk and parses it when
        the last part arrives (that answer waits at least 60 s: a large file takes a while). When a
        part fails, the upload is aborted on the reconstructor too, and the error raised."""
        if not 0 < part_bytes <= IMPORT_PART_MAX_BYTES:
            raise ValueError(f"part_bytes must be in (0, {IMPORT_PART_MAX_BYTES}], got {part_bytes}")
        key = keys.MAP_IMPORT.format(map=map_id)
        upload_id = f"up-{uuid.uuid4().hex}"
        if isinstance(body, (bytes, bytearray, memoryview)):
            view = memoryview(body)
            parts = (bytes(view[i:i + part_bytes]) for i in range(0, len(view), part_bytes))
        else:
            parts = iter(lambda: body.read(part_bytes), b"")
        offset, part = 0, next(parts, b"")
        if not part:
            raise ValueError(f"{filename}: nothing to import (no bytes)")
        try:
            while True:
                following = next(parts, b"")  # one part ahead: is this the last one?
                req = MapImportRequest(map_id=map_id, filename=filename, data=part, upload_id=upload_id,
                                       offset=offset, last=not following)
                if not following:
                    return self.bus.request(key, req, MapInfo, timeout_s=timeout_s or max(self.timeout_s, 60.0))
                self.bus.request(key, req, MapImportProgress, timeout_s=self.timeout_s)
                offset, part = offset + len(part), following
        except BaseException:
            # Best effort: the reconstructor drops an upload on its own failure, or when idle, anyway.
            with contextlib.suppress(Exception):
                self.bus.request(key, MapImportRequest(map_id=map_id, filename=filename, upload_id=upload_id,
                                                       offset=offset, abort=True, last=False),
                                 MapImportProgress, timeout_s=min(self.timeout_s, 5.0))
            raise

    def chunks(self, map_id: str, version: int | None = None, max_points: int = 1_000_000) -> Iterator[MapChunk]:
        """Every chunk of one version of a map, in order."""
        index, count = 0, 1
        while index < count:
            chunk = self.bus.request(keys.MAP_CHUNK.format(map=map_id),
                                     MapChunkRequest(map_id=map_id, version=version, index=index,
                                                     max_points=max_points),
                                     MapChunk, timeout_s=self.timeout_s)
            version, count = chunk.version, chunk.count  # pin the version the first chunk came from
            index += 1
            yield chunk

    def build(self, req: BuildMapRequest, *, on_event: Callable[[JobEvent], None] | None = None,
              cancel: threading.Event | None = None) -> MapInfo:
        """Run a map build job on the reconstructor to its end; ``on_event`` sees its progress.

        The budget is per event (``build_stall_s`` without one fails), not for the whole build: a large
        map takes long, a dead reconstructor is noticed as soon as it stops talking. ``cancel`` set
        cancels the build on the reconstructor too (:meth:`cancel_build`) and raises
        :class:`~shared.jobs.Cancelled` once it ended so (a build that stored its map before the cancel
        reached it returns that map)."""
        end = await_job(self.bus, keys.MAP_BUILD.format(map=req.map_id), req,
                        keys.MAP_BUILD_EVENTS.format(map=req.map_id, build=req.build_id), on_event=on_event,
                        stall_s=self.build_stall_s, submit_timeout_s=self.timeout_s, cancel=cancel,
                        cancel_remote=lambda: self.cancel_build(req.map_id, req.build_id))
        if not isinstance(end.data, MapBuildFinished):
            raise JobFailedError(f"map build {req.build_id} ended without its map ({type(end.data).__name__})")
        return end.data.info


    def cancel_build(self, map_id: str, build_id: str) -> list[JobAccepted | RemoteError]:
        """Ask every reconstructor to cancel a build of ``map_id`` (the answers, each accepted or not)."""
        return self.bus.request_all(keys.MAP_BUILD_CANCEL.format(map=map_id), BuildCancelRequest(build_id=build_id),
                                    JobAccepted, timeout_s=min(self.timeout_s, 10.0))


class RendererClient:
    def __init__(self, bus: TypedBus, *, timeout_s: float = 30.0):
        self.bus, self.timeout_s = bus, timeout_s

    def views(self, map_id: str, views: list[ViewPose], camera: CameraIntrinsics | None = None,
              with_labels: bool = True, splat_mode: SplatMode | None = None) -> RenderResult:
        req = RenderRequest(map_id=map_id, views=views, camera=camera or CameraIntrinsics(), with_labels=with_labels,
                            splat_mode=splat_mode)
        return self.bus.request(keys.RENDER_VIEWS.format(), req, RenderResult, timeout_s=self.timeout_s,
                                balance="renderer")

    def spatial_map(self, map_id: str, pose: Pose, trajectory_m: np.ndarray | None = None,
                    candidates: list[Candidate] | None = None, **kw) -> SpatialMapResult:
        req = SpatialMapRequest(map_id=map_id, pose=pose, trajectory_m=trajectory_m, candidates=candidates or [], **kw)
        return self.bus.request(keys.RENDER_MAP.format(), req, SpatialMapResult, timeout_s=self.timeout_s,
                                balance="renderer")


__all__ = ["MapClient", "MapperClient", "PlannerClient", "RendererClient", "RobotClient", "ServicesClient"]
