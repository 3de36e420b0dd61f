"""The robot port and its embedded simulator backend.

``Robot`` is the only interface the rest of robot-io (the bus adapter) uses. A backend registers
itself in ``ROBOTS`` under a name with a typed config::

    robot = ROBOTS.create("sim", {"scene": "generated:3:floors=2"})
    pano = robot.observe()                       # 12 RGB-D(-semantic) views + pose
    result = robot.move_to(1.0, 0.5)             # world-axis offset; reached / blocked
    with robot.recording(sink, rate_hz=10.0):    # frames at a fixed simulated rate
        robot.look_around()

Adding a backend (no other service changes; they only see the bus messages):

* **Habitat-sim**: ``observe`` renders 12 views by rotating the agent's RGB-D(-semantic) sensors
  (Habitat is y-up: convert every position with ``shared.geometry.habitat_to_world`` and rotations
  with ``habitat_quaternion_to_heading``, once, inside the backend); ``move_to`` turns to
  ``atan2(dy, dx)`` and calls ``sim.step("move_forward")`` (0.25 m, navmesh sliding) until the
  waypoint or a collision; ``geodesic_distance`` / ``shortest_path`` map to ``sim.pathfinder``.
* **ROS 2 robot** (``"ros2"``, :mod:`services.robot_io.core.ros2.backend`): a real body over zenoh
  (zenoh-bridge-ros2dds or rmw_zenoh keys), CDR through rosbags; closed-loop turns and drives on
  odometry, deadlines, a zero Twist on every exit; profiles ``stretch`` and ``generic`` as data.

Every backend must keep these semantics: world frame z-up, heading from +x towards +y, positive
turns are left (counter-clockwise), panorama view i looks at ``heading - i * 30 deg``.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from shared.geometry import camera_pose, panorama_headings, wrap_angle
from shared.registry import BackendConfig, Registry
from shared.schemas import (
    CameraIntrinsics, Frame, MoveResult, MoveStatus, Panorama, Pose, RenderResult, SceneSummary, ViewPose,
)

from libs.world.errors import NoWalkableAreaError, PoseOffGroundError
from libs.world.info import describe_scene
from libs.world.navgrid import AgentShape, NavGrid
from libs.world.scene import Scene, load_scene

from .errors import RobotIOError
from .render import SceneRenderer
from .sensors import SensorNoise, SensorNoiseConfig

log = logging.getLogger(__name__)

FrameSink = Callable[[Frame], None]


class Robot(ABC):
    """The robot port: perception, motion and recording, in world coordinates (z up)."""

    @property
    @abstractmethod
    def pose(self) -> Pose:
        """The agent's pose as the robot reports it (odometry; equals the truth without drift)."""

    @property
    @abstractmethod
    def camera(self) -> CameraIntrinsics:
        """The default camera of ``observe``."""

    @abstractmethod
    def observe(self, camera: CameraIntrinsics | None = None, with_semantic: bool = True) -> Panorama:
        """A panorama of ``views`` views (view i at heading - i * 30 deg), RGB-D(-semantic) + pose."""

    @abstractmethod
    def move_to(self, dx_m: float, dy_m: float) -> MoveResult:
        """Turn to atan2(dy, dx) and walk straight towards pose + (dx, dy) (world axes)."""

    @abstractmethod
    def turn(self, angle_rad: float) -> Pose:
        """Turn in place; positive is left (counter-clockwise)."""

    @abstractmethod
    def look_around(self) -> list[Frame]:
        """Sweep the camera +-60 deg in yaw and +-45 deg in pitch; the frames of the sweep."""

    @abstractmethod
    def reset(self, pose: Pose | None = None) -> Pose:
        """Place the agent at ``pose`` (snapped to walkable ground) or the scene's start pose."""

    @abstractmethod
    def scene_info(self) -> SceneSummary:
        """What the robot knows about its world: name, bounds, rooms, objects, labels, walkable area."""

    @abstractmethod
    def recording(self, sink: FrameSink, rate_hz: float = 10.0) -> contextlib.AbstractContextManager[None]:
        """While open, every motion emits ``Frame``s at ``rate_hz`` of (simulated) time to ``sink``."""

    def geodesic_distance(self, start_m, goal_m) -> float:
        raise NotImplementedError(f"{type(self).__name__} has no map for geodesic queries")

    def shortest_path(self, start_m, goal_m) -> np.ndarray | None:
        raise NotImplementedError(f"{type(self).__name__} has no map for path queries")

    def halt(self) -> None:
        """Stop any motion now, from any thread, even while a command runs (shutdown, SIGTERM).
        The command in progress ends with an error. A simulator has nothing to stop."""

    def off_ground_m(self, p) -> float | None:
        """How far ``p`` is from walkable ground (None: this backend cannot tell)."""
        return None

    def scene_views(self, views: list[ViewPose], camera: CameraIntrinsics | None = None,
                    with_semantic: bool = True) -> RenderResult:
        """Views at floor poses given in the reported frame, ray-cast from the true scene: what a perfect
        map would render there. Only a simulator has the scene (an evaluation control, issue 20)."""
        raise RobotIOError(f"{type(self).__name__} has no scene to ray-cast: true-scene views exist in simulation only")

    def transaction(self) -> contextlib.AbstractContextManager[None]:
        """Around one request: when it fails, the robot's state is left exactly as it was. A
        simulator restores its state; a real robot cannot undo a motion and keeps reporting
        where it really is."""
        return contextlib.nullcontext()

    def health(self) -> str | None:
        """None while the robot's state is usable, else what is wrong with it (shown in ``info``)."""
        return None

    def close(self) -> None:
        """Release the robot or simulator."""

    def __enter__(self) -> Robot:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


ROBOTS: Registry[Robot] = Registry("robot")


class SimConfig(BackendConfig):
    """The embedded simulator (open3d Embree ray casting of a generated house or a mesh file)."""

    scene: str = "generated:0"
    scenes_dir: str | None = None  # where relative mesh paths (episode scene_ids) are looked up
    camera: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    views: int = Field(12, ge=1, le=72)
    agent_radius_m: float = Field(0.1, gt=0.0, le=1.0)
    agent_height_m: float = Field(1.5, gt=0.2, le=3.0)
    camera_height_m: float = Field(1.25, gt=0.0, le=3.0)
    max_climb_m: float = Field(0.2, ge=0.0, le=0.5)
    nav_cell_m: float = Field(0.05, ge=0.01, le=0.5)
    step_m: float = Field(0.25, gt=0.0, le=1.0)  # forward sub-step of move_to (VLN-CE: 0.25 m)
    goal_tolerance_m: float = Field(0.1, ge=0.0, le=1.0)
    linear_speed_mps: float = Field(0.5, gt=0.0)  # simulated time for recordings
    angular_speed_dps: float = Field(60.0, gt=0.0)
    look_step_deg: float = Field(15.0, gt=0.0, le=90.0)
    record_depth: bool = True
    noise: SensorNoiseConfig = Field(default_factory=SensorNoiseConfig)
    start_pose: Pose | None = None
    render_threads: int = Field(0, ge=0)  # Embree's threads; 0: all cores
    # What renders panoramas and frames: Embree's ray caster, or the single-threaded z-buffer
    # rasteriser (same per-pixel hits; 4-5x less CPU at 256 px on the houses and Replica). "auto":
    # raster up to 12 triangles per pixel of a view (49 k at 64 x 64, 786 k at 256 x 256), below the
    # measured crossover of ~15 (render.RASTER_TRIANGLES_PER_PIXEL).
    ray_caster: Literal["auto", "embree", "raster"] = "auto"
    # reset() refuses a pose farther than this from walkable ground instead of snapping it to some
    # corner (a start pose at (1e6, 1e6) is a mistake, not a place).
    pose_tolerance_m: float = Field(1.0, gt=0.0, le=100.0)

    @field_validator("scene")
    @classmethod
    def _scene_nonempty(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("scene must name a generated house or a mesh file")
        return v


@ROBOTS.register("sim", SimConfig)
class SimRobot(Robot):
    """A simulated robot in a :class:`Scene`; owns the renderer and the navigation grid."""

    def __init__(self, config: SimConfig | None = None, scene: Scene | None = None):
        self.config = config or SimConfig()
        self.scene = scene if scene is not None else load_scene(self.config.scene, self.config.scenes_dir)
        self.renderer = SceneRenderer(self.scene, nthreads=self.config.render_threads, ray_caster=self.config.ray_caster)
        self.agent = AgentShape(self.config.agent_radius_m, self.config.agent_height_m, self.config.max_climb_m)
        self.nav = NavGrid(self.scene, self.agent, self.config.nav_cell_m, self.renderer.raycasting_scene)
        if len(self.nav.nodes_m) == 0:
            a = self.agent
            raise NoWalkableAreaError(
                f"scene {self.scene.name!r} has no walkable floor for this agent (radius {a.radius_m:.2f} m, "
                f"height {a.height_m:.2f} m): no upward floor with that headroom is wider than the agent")
        self.noise = SensorNoise(self.config.noise)
        self._sinks: list[tuple[FrameSink, float]] = []
        self._clock_s = 0.0
        self._next_frame_s = 0.0
        self._frame_index = 0
        self._pitch = 0.0
        start = self.config.start_pose or self.scene.start_pose
        if start is not None:
            self.nav.set_main_component_from(start.xyz)
        self.reset(self.config.start_pose)

    # --- state ---------------------------------------------------------------------------------------

    @property
    def true_pose(self) -> Pose:
        return Pose(position_m=tuple(float(v) for v in self._pos), heading_rad=float(self._heading))

    @property
    def pose(self) -> Pose:
        return self.noise.odometry(self.true_pose)

    @property
    def camera(self) -> CameraIntrinsics:
        return self.config.camera

    @property
    def clock_s(self) -> float:
        """Simulated time (s) since creation; advances with motion."""
        return self._clock_s

    def scene_info(self) -> SceneSummary:
        return describe_scene(self.scene, self.nav)

    def reset(self, pose: Pose | None = None) -> Pose:
        if pose is None:
            pose = self.scene.start_pose
        if pose is None:
            # A mesh without a start: the walkable point nearest the middle of the main region.
            main = self.nav.nodes_m[self.nav.component == self.nav.main_component]
            centre = np.median(main, axis=0)
            pose = Pose(position_m=tuple(main[np.argmin(np.linalg.norm(main - centre, axis=1))]), heading_rad=0.0)
        p = pose.xyz
        node = self.nav.locate(p, z_tol_m=0.3)
        pos = self.nav.nodes_m[node].copy() if node >= 0 else self.nav.snap(p, main_only=True)
        if node >= 0:
            pos[:2] = p[:2]  # keep the exact xy inside the cell
        off = float(np.linalg.norm(pos - p))
        if off > self.config.pose_tolerance_m:
            raise PoseOffGroundError(off, self.config.pose_tolerance_m)
        self._pos = pos
        self._heading = float(wrap_angle(pose.heading_rad))
        self._pitch = 0.0
        self.noise.reset(self.true_pose)
        return self.pose

    def off_ground_m(self, p) -> float:
        """How far ``p`` is from the walkable ground of the main region (0 on it)."""
        p = np.asarray(p, dtype=np.float64)
        node = self.nav.locate(p, z_tol_m=0.3)
        if node >= 0 and self.nav.component[node] == self.nav.main_component:
            return 0.0
        return float(np.linalg.norm(self.nav.snap(p, main_only=True) - p))

    # --- atomicity and health ------------------------------------------------------------------------

    def _state(self) -> tuple:
        return (self._pos.copy(), self._heading, self._pitch, self._clock_s, self._next_frame_s,
                self._frame_index, copy.deepcopy(self.noise))

    @contextlib.contextmanager
    def transaction(self) -> Iterator[None]:
        saved = self._state()
        try:
            yield
        except BaseException:
            (self._pos, self._heading, self._pitch, self._clock_s, self._next_frame_s, self._frame_index,
             self.noise) = saved
            raise

    def health(self) -> str | None:
        values = (*self._pos, self._heading, self._pitch, self._clock_s)
        if not all(math.isfinite(float(v)) for v in values):
            return f"robot state is not finite (position {self._pos.tolist()}, heading {self._heading})"
        off = self.off_ground_m(self._pos)
        if off > self.config.pose_tolerance_m:
            return f"the robot is {off:.2f} m from walkable ground"
        return None

    # --- perception ----------------------------------------------------------------------------------

    def observe(self, camera: CameraIntrinsics | None = None, with_semantic: bool = True) -> Panorama:
        cam = camera or self.config.camera
        headings = panorama_headings(self._heading, self.config.views)
        out = self.renderer.render_views(
            self._pos, headings, cam.pinhole(), 0.0, self.config.camera_height_m, with_semantic=with_semantic
        )
        depth = self.noise.depth(out.depth_m)
        reported = self.pose
        # Headings are reported in the robot's (odometry) frame, like the pose.
        rep_headings = panorama_headings(reported.heading_rad, self.config.views)
        return Panorama(
            pose=reported,
            camera=cam,
            headings_rad=np.asarray(rep_headings, dtype=np.float64),
            rgb=out.rgb,
            depth_m=depth,
            semantic=out.semantic if with_semantic else None,
            timestamp_s=self._clock_s,
            depth_noise_rel=self.noise.config.depth_noise_rel,
        )

    def scene_views(self, views: list[ViewPose], camera: CameraIntrinsics | None = None,
                    with_semantic: bool = True) -> RenderResult:
        cam = camera or self.config.camera
        # A view is given in the reported (odometry) frame, like a candidate: keep its offset from the
        # reported pose and apply it to the true one, so drift moves the view with the robot.
        rep, true = self.pose, self.true_pose
        turn = true.heading_rad - rep.heading_rad
        c, s = math.cos(turn), math.sin(turn)
        poses = []
        for v in views:
            d = np.subtract(v.position_m, rep.position_m)
            xyz = np.add(true.position_m, [c * d[0] - s * d[1], s * d[0] + c * d[1], d[2]])
            poses.append(camera_pose(xyz, v.heading_rad + turn, v.pitch_rad, self.config.camera_height_m))
        out = self.renderer.render(np.stack(poses), cam.pinhole(), with_semantic=with_semantic)
        depth = np.asarray(out.depth_m, np.float32)
        return RenderResult(map_id="true-scene", version=1, rgb=out.rgb, depth_m=depth, hole_mask=~(depth > 0),
                            labels=out.semantic if with_semantic else None)

    def render_frame(self, pitch_rad: float = 0.0) -> Frame:
        """One forward view at the current pose (what a recording emits)."""
        cam = self.config.camera
        out = self.renderer.render_views(self._pos, np.array([self._heading]), cam.pinhole(), pitch_rad, self.config.camera_height_m)
        frame = Frame(
            index=self._frame_index,
            timestamp_s=self._clock_s,
            pose=self.pose,
            pitch_rad=pitch_rad,
            imu_heading_rad=self.noise.imu_heading(self._heading),
            camera=cam,
            rgb=out.rgb[0],
            depth_m=self.noise.depth(out.depth_m[0]) if self.config.record_depth else None,
            semantic=out.semantic[0] if out.semantic is not None else None,
            depth_noise_rel=self.noise.config.depth_noise_rel if self.config.record_depth else 0.0,
        )
        self._frame_index += 1
        return frame

    # --- motion --------------------------------------------------------------------------------------

    def turn(self, angle_rad: float) -> Pose:
        self._rotate_to(self._heading + angle_rad, self._pitch)
        return self.pose

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult:
        dist = math.hypot(dx_m, dy_m)
        start = self._pos.copy()
        if dist < 1e-9:
            return MoveResult(status=MoveStatus.REACHED, pose=self.pose, travelled_m=0.0, steps=0)
        self._rotate_to(math.atan2(dy_m, dx_m), 0.0)
        target = start[:2] + np.array([dx_m, dy_m])
        step = self.config.step_m
        travelled, steps, stalls = 0.0, 0, 0
        max_steps = int(math.ceil(dist / step)) + 8
        while steps < max_steps:
            rem = target - self._pos[:2]
            rem_d = float(np.hypot(*rem))
            if rem_d <= 1e-6:
                break
            d = min(step, rem_d)
            u = rem / rem_d
            new = self._try_step(u * d)
            moved = float(np.hypot(*(new[:2] - self._pos[:2])))
            steps += 1
            if moved < 1e-3:
                break
            progress = rem_d - float(np.hypot(*(target - new[:2])))
            self._advance_to(new)
            travelled += moved
            # Sliding along a wall that leads nowhere: stop, like a VLN-CE agent that collides.
            stalls = stalls + 1 if progress < 0.25 * d else 0
            if stalls >= 2:
                break
        remaining = float(np.hypot(*(target - self._pos[:2])))
        status = MoveStatus.REACHED if remaining <= self.config.goal_tolerance_m else MoveStatus.BLOCKED
        self.noise.on_motion(travelled, 0.0)
        return MoveResult(status=status, pose=self.pose, travelled_m=travelled, steps=steps)

    def _try_step(self, delta: np.ndarray) -> np.ndarray:
        """Where one sub-step along ``delta`` ends: full, slid along an axis, or partial."""
        goal = np.array([self._pos[0] + delta[0], self._pos[1] + delta[1], self._pos[2]])
        end, ok = self.nav.walk(self._pos, goal)
        if ok:
            return end
        # Slide: keep the component of the motion along the obstacle (grid walls are axis-aligned).
        best, best_gain = None, 0.0
        for axis in (0, 1):
            if abs(delta[axis]) < 1e-6:
                continue
            d2 = np.zeros(2)
            d2[axis] = delta[axis]
            g = np.array([self._pos[0] + d2[0], self._pos[1] + d2[1], self._pos[2]])
            e, ok2 = self.nav.walk(self._pos, g)
            gain = float(np.dot(e[:2] - self._pos[:2], delta))
            if gain > best_gain:
                best, best_gain = e, gain
        partial_gain = float(np.dot(end[:2] - self._pos[:2], delta))
        if best is not None and best_gain > partial_gain:
            return best
        return end

    def _advance_to(self, new: np.ndarray) -> None:
        a = self._pos.copy()
        dur = float(np.linalg.norm(new - a)) / self.config.linear_speed_mps
        self._emit_during(dur, lambda f: (a + f * (new - a), self._heading, self._pitch))
        self._pos = new

    def _rotate_to(self, heading_rad: float, pitch_rad: float) -> None:
        h0, p0 = self._heading, self._pitch
        dh = float(wrap_angle(heading_rad - h0))
        dp = pitch_rad - p0
        ang = math.degrees(max(abs(dh), abs(dp)))
        dur = ang / self.config.angular_speed_dps
        pos = self._pos.copy()
        self._emit_during(dur, lambda f: (pos, h0 + f * dh, p0 + f * dp))
        self._heading = float(wrap_angle(h0 + dh))
        self._pitch = pitch_rad
        self.noise.on_motion(0.0, abs(dh))

    def _emit_during(self, duration_s: float, at: Callable[[float], tuple]) -> None:
        """Advance the clock; emit frames at the fixed rate of each open recording."""
        t0, t1 = self._clock_s, self._clock_s + duration_s
        if self._sinks:
            period = 1.0 / self._sinks[-1][1]
            saved = (self._pos, self._heading, self._pitch)
            while self._next_frame_s <= t1 + 1e-9:
                f = 1.0 if duration_s <= 0 else min(1.0, max(0.0, (self._next_frame_s - t0) / duration_s))
                pos, head, pitch = at(f)
                self._pos, self._heading = np.asarray(pos, dtype=np.float64), float(wrap_angle(head))
                self._clock_s = self._next_frame_s
                frame = self.render_frame(pitch)
                for sink, _ in self._sinks:
                    sink(frame)
                self._next_frame_s += period
            self._pos, self._heading, self._pitch = saved
        self._clock_s = t1

    def look_around(self) -> list[Frame]:
        """Yaw sweep 0 -> +60 -> -60 -> 0 at pitch 0, +45 and -45; one frame per angular step."""
        h0 = self._heading
        step = math.radians(self.config.look_step_deg)
        yaw = math.radians(60.0)
        pitch = math.radians(45.0)
        waypoints = [(0.0, 0.0), (yaw, 0.0), (-yaw, 0.0), (-yaw, pitch), (yaw, pitch), (yaw, -pitch), (-yaw, -pitch), (0.0, 0.0)]
        frames: list[Frame] = []
        cur = (0.0, 0.0)
        frames.append(self._frame_at(h0, 0.0))
        for wy, wp in waypoints[1:]:
            n = max(1, int(round(max(abs(wy - cur[0]), abs(wp - cur[1])) / step)))
            for k in range(1, n + 1):
                y = cur[0] + (wy - cur[0]) * k / n
                p = cur[1] + (wp - cur[1]) * k / n
                self._rotate_to(h0 + y, p)
                frames.append(self._frame_at(self._heading, self._pitch))
            cur = (wy, wp)
        self._heading, self._pitch = float(wrap_angle(h0)), 0.0
        return frames

    def _frame_at(self, heading: float, pitch: float) -> Frame:
        self._heading = float(wrap_angle(heading))
        return self.render_frame(pitch)

    @contextlib.contextmanager
    def recording(self, sink: FrameSink, rate_hz: float = 10.0) -> Iterator[None]:
        if not rate_hz > 0:
            raise RobotIOError(f"rate_hz must be positive, got {rate_hz}")
        entry = (sink, float(rate_hz))
        self._sinks.append(entry)
        self._next_frame_s = self._clock_s
        try:
            yield
        finally:
            self._sinks.remove(entry)

    # --- maps ----------------------------------------------------------------------------------------

    def geodesic_distance(self, start_m, goal_m) -> float:
        return self.nav.geodesic_distance(start_m, goal_m)

    def shortest_path(self, start_m, goal_m) -> np.ndarray | None:
        return self.nav.shortest_path(start_m, goal_m)
