"""robot-io service: the only process that touches a robot or simulator.

A thin adapter: each queryable decodes its request, calls the :class:`Robot` port (one call at a
time - a robot has one body), and encodes the reply. While a recording is on, the frames the robot
emits are published on ``IO_FRAMES/{recording}`` for the reconstructor.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from services.robot_io import ros2_zenoh  # noqa: F401  (registers the zenoh transport of the ros2 backend)
from libs.world import SceneError, SceneNotFoundError
from services.robot_io.core import REFUSALS, ROBOTS, Robot
from libs.world.scene import is_generated_spec
from shared.bus.typed import NotFound
from shared import keys
from shared.runner import Node, Service, ServiceSettings
from shared.schemas import (
    Frame, GeodesicReply, GeodesicRequest, LoadSceneRequest, MoveRequest, MoveResult, ObserveRequest, Panorama, Ping,
    PoseReply, RecordReply, RecordRequest, RenderResult, ResetRequest, SceneSummary, SceneViewsRequest, TurnRequest,
)

log = logging.getLogger(__name__)


class RobotIoSettings(ServiceSettings):
    # Field names are unique across services so that one environment can configure them all.
    robot_backend: str = Field("sim", description="robot backend (registered in services.robot_io.core.ROBOTS)")
    robot_config: dict[str, Any] = Field(default_factory=dict, description="the backend's typed config")
    scene_dirs: list[str] = Field(default_factory=list, description=(
        "directories scene files may be loaded from over the bus (besides the backend's scenes_dir); "
        "a path elsewhere is refused without looking at it"))


def _config_fields(backend: str) -> set[str]:
    return set(ROBOTS.config_class(backend).model_fields)


def downscale_frame(frame: Frame, max_width_px: int | None) -> Frame:
    """Shrink a frame by an integer factor, keeping the field of view (pinhole stays exact).

    Colour is area-averaged; depth and labels take the top-left sample of each block (averaging
    depth across an edge would invent surfaces that do not exist).
    """
    w = frame.camera.width_px
    if max_width_px is None or w <= max_width_px:
        return frame
    f = -(-w // max_width_px)
    h2, w2 = frame.camera.height_px // f, w // f
    rgb = cv2.resize(np.ascontiguousarray(frame.rgb[: h2 * f, : w2 * f]), (w2, h2), interpolation=cv2.INTER_AREA)
    # The pixel centre of block (i, j) is its centre, not its corner: sample the middle pixel.
    o = f // 2
    depth = None if frame.depth_m is None else np.ascontiguousarray(frame.depth_m[o::f, o::f][:h2, :w2])
    sem = None if frame.semantic is None else np.ascontiguousarray(frame.semantic[o::f, o::f][:h2, :w2])
    cam = frame.camera.model_copy(update={"width_px": w2, "height_px": h2})
    return frame.model_copy(update={"rgb": rgb, "depth_m": depth, "semantic": sem, "camera": cam})


class RobotIoService(Service[RobotIoSettings]):
    name = "robot_io"
    Settings = RobotIoSettings

    def __init__(self, settings: RobotIoSettings, robot: Robot | None = None):
        super().__init__(settings)
        self.robot = robot or ROBOTS.create(settings.robot_backend, settings.robot_config)
        # One body: motions, observations and recordings are serialised.
        self._lock = threading.RLock()
        self._recordings: dict[str, tuple[Any, list[int]]] = {}
        self._node: Node | None = None

    def backends(self) -> dict[str, str]:
        return {"robot": self.settings.robot_backend}

    def start(self, node: Node) -> None:
        self._node = node
        r = node.robot
        # One worker per endpoint: the lock serialises anyway, and order of motions matters.
        node.serve(keys.IO_OBSERVE.format(robot=r), ObserveRequest, self.observe, workers=1)
        node.serve(keys.IO_MOVE.format(robot=r), MoveRequest, self.move_to, workers=1)
        node.serve(keys.IO_TURN.format(robot=r), TurnRequest, self.turn, workers=1)
        node.serve(keys.IO_LOOK.format(robot=r), Ping, self.look_around, workers=1)
        node.serve(keys.IO_RESET.format(robot=r), ResetRequest, self.reset, workers=1)
        node.serve(keys.IO_RECORD.format(robot=r), RecordRequest, self.record, workers=1)
        node.serve(keys.IO_GEODESIC.format(robot=r), GeodesicRequest, self.geodesic, workers=2)
        node.serve(keys.IO_VIEWS.format(robot=r), SceneViewsRequest, self.scene_views, workers=1)
        node.serve(keys.IO_SCENE.format(robot=r), Ping, self.scene, workers=1)
        node.serve(keys.IO_LOAD_SCENE.format(robot=r), LoadSceneRequest, self.load_scene, workers=1)

    def stop(self) -> None:
        # Before the lock: a motion in progress holds it, and a robot must stop now, not after it.
        self.robot.halt()
        with self._lock:
            for ctx, _ in self._recordings.values():
                ctx.__exit__(None, None, None)
            self._recordings.clear()
            self.robot.close()

    # --- handlers ------------------------------------------------------------------------------------
    def _publish_pose(self) -> None:
        if self._node:
            self._node.bus.publish(keys.IO_POSE.format(robot=self._node.robot), self.robot.pose)

    def health(self) -> str | None:
        # Without the lock: a reading taken beside a running motion is still a reading, and the
        # info queryable must answer while a long sweep holds the body.
        return self.robot.health()

    @contextlib.contextmanager
    def _body(self) -> Iterator[None]:
        """One request on the robot's one body: serialised, and undone when it fails (a failed
        request leaves the robot's state exactly as it was)."""
        with self._lock, self.robot.transaction():
            yield

    def observe(self, req: ObserveRequest) -> Panorama:
        with self._body():
            return self.robot.observe(req.camera, with_semantic=req.with_semantic)

    def scene_views(self, req: SceneViewsRequest) -> RenderResult:
        # The body's lock: the views follow the robot's pose, which must not move meanwhile.
        with self._lock:
            try:
                return self.robot.scene_views(req.views, req.camera, with_semantic=req.with_semantic)
            except REFUSALS as exc:  # a real robot: a refused request, the service keeps serving
                raise ValueError(str(exc)) from None

    def move_to(self, req: MoveRequest) -> MoveResult:
        with self._body():
            result = self.robot.move_to(req.dx_m, req.dy_m)
        self._publish_pose()
        return result

    def turn(self, req: TurnRequest) -> PoseReply:
        with self._body():
            pose = self.robot.turn(req.angle_rad)
        self._publish_pose()
        return PoseReply(pose=pose)

    def look_around(self, _: Ping) -> PoseReply:
        # The sweep's frames reach subscribers through an open recording; the reply is the pose.
        with self._body():
            self.robot.look_around()
            return PoseReply(pose=self.robot.pose)

    def reset(self, req: ResetRequest) -> PoseReply:
        with self._body():
            pose = self.robot.reset(req.pose)
        self._publish_pose()
        return PoseReply(pose=pose)

    def record(self, req: RecordRequest) -> RecordReply:
        with self._lock:
            if req.start:
                if req.recording in self._recordings:
                    raise ValueError(f"recording {req.recording!r} is already on")
                key = keys.IO_FRAMES.format(robot=self._node.robot, recording=req.recording)
                counter = [0]

                def sink(frame: Frame, key=key, counter=counter, width=req.max_width_px) -> None:
                    counter[0] += 1
                    self._node.bus.publish(key, downscale_frame(frame, width))

                ctx = self.robot.recording(sink, req.rate_hz)
                ctx.__enter__()
                self._recordings[req.recording] = (ctx, counter)
                return RecordReply(recording=req.recording, recording_on=True, frame_count=0)
            if req.recording not in self._recordings:
                raise ValueError(f"no recording {req.recording!r} is on")
            ctx, counter = self._recordings.pop(req.recording)
            ctx.__exit__(None, None, None)
            return RecordReply(recording=req.recording, recording_on=False, frame_count=counter[0])

    def geodesic(self, req: GeodesicRequest) -> GeodesicReply:
        off = {"start_off_m": self.robot.off_ground_m(req.start_m), "goal_off_m": self.robot.off_ground_m(req.goal_m)}
        d = float(self.robot.geodesic_distance(req.start_m, req.goal_m))
        if not np.isfinite(d):
            return GeodesicReply(distance_m=None, **off)
        path = self.robot.shortest_path(req.start_m, req.goal_m)
        return GeodesicReply(distance_m=d, path_m=None if path is None else np.asarray(path, np.float64), **off)

    def scene(self, _: Ping) -> SceneSummary:
        return self.robot.scene_info()

    def _check_scene_path(self, spec: str) -> None:
        """A scene file must lie inside a configured scene directory: the bus must not become a way to
        probe which paths exist on this host (the answer to a path elsewhere never depends on it)."""
        if is_generated_spec(spec):
            return
        s: RobotIoSettings = self.settings  # type: ignore[assignment]
        dirs = [*s.scene_dirs, *([s.robot_config["scenes_dir"]] if s.robot_config.get("scenes_dir") else [])]
        if not dirs:
            raise ValueError("no scene directory is configured: only generated:<seed> scenes can be loaded")
        p = Path(spec)
        roots = [Path(d).resolve() for d in dirs]
        candidates = [p.resolve()] if p.is_absolute() else [(r / p).resolve() for r in roots]
        if not any(c.is_relative_to(r) for c in candidates for r in roots):
            raise ValueError(f"scene files are loaded only from the configured scene directories ({len(roots)})")

    def load_scene(self, req: LoadSceneRequest) -> SceneSummary:
        s = self.settings
        if "scene" not in _config_fields(s.robot_backend):
            raise ValueError(f"the {s.robot_backend!r} robot backend cannot load scenes")
        self._check_scene_path(req.scene)
        with self._lock:
            if self._recordings:
                raise ValueError("cannot switch scenes while a recording is on")
            try:  # build the new robot first: a failure leaves the current scene in place
                robot = ROBOTS.create(s.robot_backend, {**s.robot_config, "scene": req.scene})
            except SceneNotFoundError as exc:
                raise NotFound(str(exc)) from None
            except SceneError as exc:
                raise ValueError(str(exc)) from None
            old, self.robot = self.robot, robot
            old.close()
        self._publish_pose()
        return self.robot.scene_info()
