"""The ``ros2`` robot backend: the Robot port on a real ROS 2 body, over zenoh, in pure Python.

* ``observe``: turn in place through the 12 headings (closed loop on odometry yaw), settle, take
  colour and depth matched by stamp, resample them to the requested pinhole camera with the
  intrinsics from camera_info (a robot without depth gives views without depth).
* ``move_to``: turn, then drive with a closed-loop controller on odometry under velocity and
  acceleration limits; stop at the safety distance from obstacles seen in the scan or depth and
  report ``blocked`` (also when odometry shows no progress: the base is pushing against something).
* Every command has a deadline. A zero Twist is sent on every exit of a motion - done, timeout,
  exception, ``close`` (shutdown, SIGTERM through the service runner) - so the robot is never left
  moving. Odometry or camera data older than ``max_data_age_s`` is :class:`StaleDataError`.
* Nav2 motion (profile ``motion: nav2``): ``move_to`` is a NavigateToPose goal to the robot's
  bt_navigator, ``turn`` and ``look_around`` are Spin goals to its behavior_server; the goal's feedback
  and status are followed, the goal is cancelled on our deadline, a halt or a lost link, and Nav2's
  result codes become our outcomes (:data:`NAV2_ERROR_OUTCOMES`). An action server that does not
  answer at connect leaves that motion on the cmd_vel controller.
* ``reset`` needs the profile's teleport service; else :class:`ResetUnsupportedError`.
* Geodesic queries come from the map topic when it is published, else NotImplementedError.
* Poses: odometry, or with the profile's ``map_frame`` the robot's localisation: odometry composed
  with the newest ``map -> odom`` transform on ``tf`` (nav2's AMCL, slam_toolbox). The controllers
  steer on that pose each tick, as nav2's controllers re-transform their goal into odometry: a
  localisation update moves the goal, not the base's own odometry.

Robot time is the clock topic when the profile has one (simulators, ``use_sim_time``), else wall
time (a robot whose clock is synchronised with ours, as ROS 2 requires anyway).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from enum import StrEnum

from shared.geometry import panorama_headings, planar_apply, wrap_angle
from shared.registry import BackendConfig
from shared.schemas import CameraIntrinsics, Frame, MoveResult, MoveStatus, Panorama, Pose, SceneSummary

from libs.ros2 import messages as m
from libs.ros2.action import ActionClient, ActionError, ClientGoal, GoalStatus, duration
from libs.ros2.keys import Qos, key_style
from libs.ros2.node import Received, Ros2Node
from libs.ros2.profiles import Motion, Ros2Profile, profile
from libs.ros2.transport import TRANSPORTS, Ros2Transport, TransportError

from ..errors import RobotIOError
from ..robot import ROBOTS, FrameSink, Robot

log = logging.getLogger(__name__)


class Ros2Error(RobotIOError):
    """Base of the ros2 backend's typed errors."""


class RobotUnavailableError(Ros2Error):
    """The robot's topics did not appear (not connected, wrong key style, domain or namespace)."""


class StaleDataError(Ros2Error):
    """Odometry or camera data is older than allowed: the robot was stopped."""


class DeadlineExceededError(Ros2Error, TimeoutError):
    """A command did not finish within its deadline: the robot was stopped."""


class RunStoppedError(Ros2Error):
    """The robot's run-stop is pressed (or the safety stop was triggered)."""


class ResetUnsupportedError(Ros2Error, ValueError):
    """``reset`` needs a teleport service, which a real robot does not have."""


class NavigationFailedError(Ros2Error):
    """Nav2 failed for a reason other than the way (TF, a missing planner or controller, its tree)."""


class GoalCanceledError(Ros2Error):
    """A Nav2 goal of ours was cancelled by someone else (an operator, another client)."""


class MotionBlockedError(Ros2Error):
    """A Spin stopped short: Nav2's collision checker saw something ahead of the turning base."""


class Nav2Outcome(StrEnum):
    BLOCKED = "blocked"  # MoveStatus.BLOCKED: set off, could not get there
    UNREACHABLE = "unreachable"  # MoveStatus.UNREACHABLE: no way there, did not set off
    TIMEOUT = "timeout"  # DeadlineExceededError
    FAULT = "fault"  # NavigationFailedError: the navigation stack itself is broken or misconfigured


# Nav2's result error codes (nav2_msgs/action: FollowPath 10x, ComputePathToPose 20x, Spin 70x; Jazzy's
# bt_navigator reports the failing server's code in NavigateToPose's result; 900x are NavigateToPose's
# own from Kilted on). A code not listed (0, 100, 200, 700: "unknown") counts as blocked.
NAV2_ERROR_OUTCOMES: dict[int, Nav2Outcome] = {
    101: Nav2Outcome.FAULT, 102: Nav2Outcome.FAULT, 103: Nav2Outcome.UNREACHABLE, 104: Nav2Outcome.BLOCKED,
    105: Nav2Outcome.BLOCKED, 106: Nav2Outcome.BLOCKED, 107: Nav2Outcome.TIMEOUT,
    201: Nav2Outcome.FAULT, 202: Nav2Outcome.FAULT, 203: Nav2Outcome.UNREACHABLE, 204: Nav2Outcome.UNREACHABLE,
    205: Nav2Outcome.BLOCKED, 206: Nav2Outcome.UNREACHABLE, 207: Nav2Outcome.UNREACHABLE,
    208: Nav2Outcome.UNREACHABLE,
    701: Nav2Outcome.TIMEOUT, 702: Nav2Outcome.FAULT, 703: Nav2Outcome.BLOCKED,
    9001: Nav2Outcome.FAULT, 9002: Nav2Outcome.FAULT, 9003: Nav2Outcome.TIMEOUT,
}


def nav2_outcome(error_code: int) -> Nav2Outcome:
    return NAV2_ERROR_OUTCOMES.get(int(error_code), Nav2Outcome.BLOCKED)


class Ros2Config(BackendConfig):
    """A ROS 2 robot over zenoh. ``profile`` names the topic set; ``profile_overrides`` edits it."""

    profile: str = "generic"
    profile_overrides: dict[str, Any] = Field(default_factory=dict)
    keys: str = Field("bridge", pattern="^(bridge|rmw_zenoh)$")
    domain_id: int = Field(0, ge=0, le=232)
    namespace: str = ""
    bridge_prefix: str = ""  # zenoh-bridge-ros2dds's own namespace option
    node_name: str = "spatialant_robot_io"
    transport: str = "zenoh"
    transport_config: dict[str, Any] = Field(default_factory=dict)
    views: int = Field(12, ge=1, le=72)
    camera: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    connect_timeout_s: float = Field(20.0, gt=0.0, le=600.0)
    max_data_age_s: float = Field(0.5, gt=0.0, le=60.0)  # robot time
    clock_timeout_s: float = Field(2.0, gt=0.0, le=60.0)  # wall time without a clock message: the robot is gone
    control_rate_hz: float = Field(20.0, ge=1.0, le=200.0)
    yaw_tolerance_deg: float = Field(1.5, gt=0.0, le=20.0)
    goal_tolerance_m: float = Field(0.1, gt=0.0, le=1.0)
    settle_s: float = Field(0.3, ge=0.0, le=10.0)
    # Turns again after a settle that found the base past yaw_tolerance_deg (see Ros2Robot._face).
    turn_corrections: int = Field(2, ge=0, le=10)
    stamp_match_s: float = Field(0.05, ge=0.0, le=1.0)  # colour/depth pairing tolerance
    turn_gain: float = Field(2.0, gt=0.0, le=20.0)
    stall_s: float = Field(1.5, gt=0.0, le=30.0)  # no progress this long while driving: blocked
    command_deadline_s: float | None = Field(None, gt=0.0, description="fixed deadline; None: from distance and limits")
    deadline_margin_s: float = Field(10.0, ge=0.0)
    look_step_deg: float = Field(15.0, gt=0.0, le=90.0)
    label_names: dict[int, str] = Field(default_factory=dict)
    bounds_min_m: tuple[float, float, float] = (-50.0, -50.0, -1.0)
    bounds_max_m: tuple[float, float, float] = (50.0, 50.0, 3.0)
    # Nav2 action calls (wall seconds). Every one is longer than zenoh's 5 s default query timeout,
    # which ends action calls through zenoh-bridge-ros2dds before the robot answers
    # (zenoh-plugin-ros2dds#413): send_goal and cancel_goal wait for a busy bt_navigator, and each
    # get_result query stays open for the goal's whole run (asked again when it still times out).
    nav2_call_timeout_s: float = Field(15.0, gt=0.0, le=120.0)
    nav2_result_timeout_s: float = Field(300.0, gt=0.0, le=3600.0)
    nav2_probe_timeout_s: float = Field(3.0, gt=0.0, le=60.0)  # is an action server there (at connect)
    nav2_cancel_wait_s: float = Field(5.0, ge=0.0, le=60.0)  # for a cancelled goal to report CANCELED


# A teleport has landed when odometry is this close to the requested pose (metres, radians), and the
# odometry of a simulator that never matches is read after this long (wall seconds).
TELEPORT_MATCH_M = 0.05
TELEPORT_MATCH_RAD = 0.05
TELEPORT_SETTLE_S = 1.0


def _same_place(a: Pose, b: Pose) -> bool:
    """Whether two poses agree in the plane (the teleport sets x, y and heading, not z)."""
    return (math.hypot(a.position_m[0] - b.position_m[0], a.position_m[1] - b.position_m[1]) <= TELEPORT_MATCH_M
            and abs(float(wrap_angle(a.heading_rad - b.heading_rad))) <= TELEPORT_MATCH_RAD)


def commanded_turn_rad(sent: list[tuple[float, float]], since_s: float, now_s: float) -> float:
    """The turn that rate commands ``sent`` ((robot time, rad/s), in order; the base at rest before the first)
    asked for between ``since_s`` and ``now_s``: each rate holds until the next command."""
    total = 0.0
    for i, (t_s, w) in enumerate(sent):
        t_end = sent[i + 1][0] if i + 1 < len(sent) else now_s
        lo, hi = max(t_s, since_s), min(t_end, now_s)
        if hi > lo:
            total += w * (hi - lo)
    return total


class _Latest:
    """The newest message of a topic with its stamp (robot time) and receive time."""

    def __init__(self, keep: int = 1):
        self._q: deque = deque(maxlen=keep)
        self.cond = threading.Condition()
        self.count = 0

    def put(self, stamp_s: float, msg: Any) -> None:
        with self.cond:
            self._q.append((stamp_s, msg))
            self.count += 1
            self.cond.notify_all()

    def get(self) -> tuple[float, Any] | None:
        with self.cond:
            return self._q[-1] if self._q else None

    def all(self) -> list[tuple[float, Any]]:
        with self.cond:
            return list(self._q)


class RobotClock:
    """Robot time: the newest clock-topic value, or wall time.

    Simulated time is not extrapolated: a simulator that stalls (rendering on a busy CPU) stops its
    own time, so its data is not stale in its own time. A clock that falls silent is caught by
    :meth:`silence_s` instead (the robot or the link is gone)."""

    def __init__(self, use_clock: bool):
        self.use_clock = use_clock
        self._last: tuple[float, float] | None = None  # (robot s, monotonic s)
        self._rate = 1.0
        self._hist: deque = deque(maxlen=50)
        self._lock = threading.Lock()

    def on_clock(self, t_s: float) -> None:
        now = time.monotonic()
        with self._lock:
            self._hist.append((t_s, now))
            (t0, w0), (t1, w1) = self._hist[0], self._hist[-1]
            if w1 - w0 > 0.2 and t1 > t0:
                self._rate = (t1 - t0) / (w1 - w0)
            self._last = (t_s, now)

    @property
    def rate(self) -> float:
        """Robot seconds per wall second (1 without a clock topic)."""
        return self._rate if self.use_clock else 1.0

    def now(self) -> float:
        if not self.use_clock:
            return time.time()
        with self._lock:
            return float("nan") if self._last is None else self._last[0]

    def silence_s(self) -> float:
        """Wall seconds since the last clock message (0 without a clock topic)."""
        if not self.use_clock:
            return 0.0
        with self._lock:
            return math.inf if self._last is None else time.monotonic() - self._last[1]

    def sleep(self, robot_s: float) -> None:
        time.sleep(max(0.0, robot_s) / max(self.rate, 1e-3))


@ROBOTS.register("ros2", Ros2Config)
class Ros2Robot(Robot):
    """A ROS 2 robot; one body: the service serialises commands; ``safety_stop`` may come from any thread."""

    def __init__(self, config: Ros2Config | None = None, transport: Ros2Transport | None = None):
        self.config = c = config or Ros2Config()
        self.profile: Ros2Profile = profile(c.profile, c.profile_overrides)
        p = self.profile
        self._owns_transport = transport is None
        self.transport = transport or TRANSPORTS.create(c.transport, c.transport_config)
        self.keys = key_style(c.keys, domain_id=c.domain_id, namespace=c.namespace, prefix=c.bridge_prefix)
        self.node = Ros2Node(self.transport, self.keys, c.node_name)
        self.clock = RobotClock(p.clock is not None)
        self._odom, self._info, self._scan, self._imu = _Latest(), _Latest(), _Latest(), _Latest()
        self._color, self._depth, self._sem = _Latest(keep=8), _Latest(keep=8), _Latest(keep=8)
        self._map = _Latest()
        self._map_odom = _Latest()  # (x, y, z), yaw: the localisation's map -> odom transform
        self._run_stopped = False
        self._safety_stopped = threading.Event()
        self._closed = False
        self.zero_twists_sent = 0
        self.cmd_published = 0
        self.nav2_cancels = 0
        self.nav2_last_goal: ClientGoal | None = None  # the newest Nav2 goal, its status and feedback
        self.control_ticks: list[float] = []  # monotonic time of each control tick (benchmarks)
        self._next_tick: float | None = None
        self._cmd = self.node.publisher(p.cmd_vel, m.MESSAGES["twist"])
        n = self.node
        if p.clock:
            n.subscribe(p.clock, m.MESSAGES["clock"], lambda msg, _i: self.clock.on_clock(m.stamp_s(msg.clock)), max_queue=64)
        n.subscribe(p.odom, m.MESSAGES["odometry"], self._stamped(self._odom), max_queue=64)
        n.subscribe(p.camera_info, m.MESSAGES["camera_info"], self._stamped(self._info))
        color_type = m.MESSAGES["compressed_image"] if p.color_encoding in ("jpeg", "png") else m.MESSAGES["image"]
        n.subscribe(p.color, color_type, self._stamped(self._color))
        if p.depth:
            depth_type = m.MESSAGES["compressed_image"] if p.depth_encoding == "compressedDepth" else m.MESSAGES["image"]
            n.subscribe(p.depth, depth_type, self._stamped(self._depth))
        if p.semantic:
            n.subscribe(p.semantic, m.MESSAGES["image"], self._stamped(self._sem))
        if p.scan:
            n.subscribe(p.scan, m.MESSAGES["scan"], self._stamped(self._scan))
        if p.imu:
            n.subscribe(p.imu, m.MESSAGES["imu"], self._stamped(self._imu), max_queue=64)
        if p.map:
            # Transient-local: a map_server publishes its map once; a backend that starts later asks
            # for it on joining instead of waiting for a re-publish that never comes.
            n.subscribe(p.map, m.MESSAGES["occupancy_grid"], self._stamped(self._map), Qos(transient_local=True, depth=1))
        if p.run_stop:
            n.subscribe(p.run_stop, m.MESSAGES["bool"], self._on_run_stop)
        if p.map_frame:
            n.subscribe(p.tf, m.MESSAGES["tf"], self._on_tf, max_queue=64)
        self._teleport = n.client(p.teleport_service, "turtlesim/srv/TeleportAbsolute") if p.teleport_service else None
        self._sinks: list[tuple[FrameSink, float]] = []
        self._frame_index = 0
        # The recording thread and look_around both make frames: an index taken twice would be dropped
        # as a repeat downstream (the reconstructor then waited its whole frame timeout for it).
        self._frame_lock = threading.Lock()
        self._rec_threads: list[tuple[threading.Event, threading.Thread]] = []
        self._map_cache: tuple[float, Any] | None = None
        self._nav: ActionClient | None = None  # NavigateToPose, when the profile moves with Nav2 and it answers
        self._spin: ActionClient | None = None
        try:
            self._wait_ready()
            if p.nav_mode_service:
                resp = n.client(p.nav_mode_service, "std_srvs/srv/Trigger").call(m.new("std_srvs/srv/Trigger_Request"), 10.0)
                if not resp.success:
                    raise RobotUnavailableError(f"{p.nav_mode_service} refused: {resp.message}")
            if p.motion == Motion.NAV2:
                self._nav = self._action(p.navigate_action, "nav2_msgs/action/NavigateToPose")
                self._spin = self._action(p.spin_action, "nav2_msgs/action/Spin") if p.spin_action else None
        except BaseException:
            self.close()
            raise

    def _action(self, name: str, action_type: str) -> ActionClient | None:
        """An action client when its server answers (a short get_result probe), else None: that
        motion stays on the cmd_vel controller."""
        c = self.config
        client = ActionClient(self.node, name, action_type, result_timeout_s=c.nav2_result_timeout_s)
        if client.server_present(c.nav2_probe_timeout_s):
            log.info("Nav2 motion: %s (%s) answers", name, action_type)
            return client
        client.close()
        log.warning("Nav2 motion: no %s action server at %s within %.0f s; that motion uses cmd_vel",
                    action_type, name, c.nav2_probe_timeout_s)
        return None

    @property
    def motion_backends(self) -> dict[str, str]:
        """Which controller each motion uses now: ``nav2`` or ``cmdvel``."""
        return {"move_to": "nav2" if self._nav else "cmdvel", "turn": "nav2" if self._spin else "cmdvel",
                "look_around": "nav2" if self._spin else "cmdvel", "observe": "cmdvel"}

    # --- inputs ------------------------------------------------------------------------------------------
    def _stamped(self, latest: _Latest):
        def on(msg, _info: Received) -> None:
            hdr = getattr(msg, "header", None)
            latest.put(m.stamp_s(hdr.stamp) if hdr is not None else self.clock.now(), msg)
        return on

    def _on_run_stop(self, msg, _info) -> None:
        self._run_stopped = bool(msg.data)
        if self._run_stopped:
            self._send_zero()

    def _on_tf(self, msg, _info) -> None:
        """Keep the newest map -> odom transform (the robot's localisation); the rest of the tree
        (odom -> base, the camera's links) is not read: odometry and camera_info carry it."""
        p = self.profile
        parent, child = p.map_frame.strip("/"), p.odom_frame.strip("/")
        for tr in msg.transforms:
            if tr.header.frame_id.strip("/") != parent or tr.child_frame_id.strip("/") != child:
                continue
            t = tr.transform.translation
            xyz = (float(t.x), float(t.y), float(t.z))
            yaw = float(m.yaw_from_quaternion(tr.transform.rotation))
            if all(map(math.isfinite, (*xyz, yaw))):  # a broken localiser's NaN must not become the pose
                self._map_odom.put(m.stamp_s(tr.header.stamp), (xyz, yaw))

    def _wait_ready(self) -> None:
        end = time.monotonic() + self.config.connect_timeout_s
        needs = [(self.profile.odom, self._odom), (self.profile.camera_info, self._info)]
        if self.profile.map_frame:
            needs.append((f"{self.profile.map_frame} -> {self.profile.odom_frame} transform on {self.profile.tf} "
                          "(is the robot's localisation running? without one, set map_frame to null)", self._map_odom))
        while time.monotonic() < end:
            if all(l.get() for _, l in needs) and (not self.clock.use_clock or not math.isnan(self.clock.now())):
                return
            time.sleep(0.05)
        missing = [t for t, l in needs if not l.get()]
        raise RobotUnavailableError(
            f"no {' or '.join(missing) or self.profile.clock} from the robot within {self.config.connect_timeout_s:.0f} s "
            f"(keys {self.config.keys}, domain {self.config.domain_id}, namespace {self.config.namespace!r})")

    # --- safety --------------------------------------------------------------------------------------------
    def _send_zero(self) -> None:
        try:
            self._cmd.publish(m.twist(0.0, 0.0))
            self.zero_twists_sent += 1
        except Exception:  # the link may be gone; nothing else can be done from here
            log.exception("could not send the zero Twist")

    def _send(self, v: float, w: float) -> None:
        self._cmd.publish(m.twist(v, w))
        self.cmd_published += 1

    def safety_stop(self) -> None:
        """Stop now and refuse motion until :meth:`clear_safety_stop` (callable from any thread)."""
        self._safety_stopped.set()
        self._send_zero()

    def halt(self) -> None:
        self.safety_stop()

    def clear_safety_stop(self) -> None:
        self._safety_stopped.clear()

    @contextlib.contextmanager
    def _motion(self, deadline_s: float, what: str) -> Iterator[float]:
        """Every motion runs inside this: it checks the preconditions and sends a zero Twist on exit."""
        if self._closed:
            raise Ros2Error("the robot connection is closed")
        self._check_safe()
        end = self.clock.now() + deadline_s
        try:
            yield end
        finally:
            for _ in range(3):  # three: one lost sample must not leave the base moving
                self._send_zero()

    def _check_safe(self) -> None:
        if self._run_stopped:
            raise RunStoppedError("the run-stop is pressed")
        if self._safety_stopped.is_set():
            raise RunStoppedError("the safety stop is on")
        if self._closed:
            raise Ros2Error("the robot connection is closed")

    def _fresh(self, latest: _Latest, topic: str) -> tuple[float, Any]:
        silent = self.clock.silence_s()
        if silent > self.config.clock_timeout_s:
            raise StaleDataError(f"{topic} is stale: no {self.profile.clock} for {silent:.1f} s (the robot or the link is gone)")
        got = latest.get()
        now = self.clock.now()
        if got is None or not (now - got[0] <= self.config.max_data_age_s):
            age = "never received" if got is None else f"{now - got[0]:.2f} s old"
            raise StaleDataError(f"{topic} is stale ({age}; allowed {self.config.max_data_age_s:.2f} s)")
        return got

    def _tick(self, end_s: float, what: str) -> None:
        self._check_safe()
        if self.clock.now() > end_s:
            raise DeadlineExceededError(f"{what} did not finish within its deadline")
        now = time.monotonic()
        self.control_ticks.append(now)
        if len(self.control_ticks) > 100_000:
            del self.control_ticks[:50_000]
        # A fixed rate, not a fixed pause: the loop's own work comes out of the period.
        period = 1.0 / (self.config.control_rate_hz * max(self.clock.rate, 1e-3))
        nxt = getattr(self, "_next_tick", None)
        if nxt is None or now - nxt > period:  # first tick of a motion, or late: restart the schedule
            nxt = now
        self._next_tick = nxt + period
        time.sleep(max(0.0, self._next_tick - now))

    # --- state ---------------------------------------------------------------------------------------------
    def _odom_pose(self, msg) -> Pose:
        pp = msg.pose.pose
        return Pose(position_m=(float(pp.position.x), float(pp.position.y), float(pp.position.z)),
                    heading_rad=float(wrap_angle(m.yaw_from_quaternion(pp.orientation))))

    def _world(self, odo: Pose) -> Pose:
        """An odometry pose in the reported frame: composed with the newest map -> odom transform
        when the profile has a localisation frame, however old (localisation corrects slowly and
        odometry carries the motion in between; AMCL and slam_toolbox republish it steadily)."""
        if not self.profile.map_frame:
            return odo
        got = self._map_odom.get()
        if got is None:
            raise StaleDataError(f"no {self.profile.map_frame} -> {self.profile.odom_frame} transform yet")
        xyz, heading = planar_apply(*got[1], odo.position_m, odo.heading_rad)
        return Pose(position_m=xyz, heading_rad=heading)

    @property
    def pose(self) -> Pose:
        got = self._odom.get()
        if got is None:
            raise StaleDataError(f"no {self.profile.odom} yet")
        return self._world(self._odom_pose(got[1]))

    @property
    def camera(self) -> CameraIntrinsics:
        return self.config.camera

    def scene_info(self) -> SceneSummary:
        lo, hi = self.config.bounds_min_m, self.config.bounds_max_m
        area, cell = 0.0, 0.05
        mp = self._map.get()
        if mp is not None:
            info = mp[1].info
            cell = float(info.resolution)
            data = np.asarray(mp[1].data)
            area = float(((data >= 0) & (data < 50)).sum()) * cell * cell
            ox, oy = float(info.origin.position.x), float(info.origin.position.y)
            lo = (ox, oy, lo[2])
            hi = (ox + info.width * cell, oy + info.height * cell, hi[2])
        # A real robot knows its bounds (from the map when there is one) and its labels, nothing more.
        return SceneSummary(scene=f"ros2:{self.config.profile}", source=f"ROS 2 robot ({self.config.keys} keys)",
                            floors=1, bounds_min_m=lo, bounds_max_m=hi, reachable_area_m2=area, nav_cell_m=cell,
                            label_names=dict(self.config.label_names))

    # --- motion ----------------------------------------------------------------------------------------------
    def _deadline(self, distance_m: float = 0.0, angle_rad: float = 0.0) -> float:
        c, p = self.config, self.profile
        if c.command_deadline_s is not None:
            return c.command_deadline_s
        return (distance_m / p.max_linear_mps + math.degrees(abs(angle_rad)) / p.max_angular_dps) * 2.0 + c.settle_s + c.deadline_margin_s

    def _rotate_to(self, heading_rad: float, end_s: float) -> None:
        """Closed-loop turn to a reported-frame heading (odometry yaw, localised with ``map_frame``)
        under the angular velocity and acceleration limits."""
        c, p = self.config, self.profile
        w_max, a_max = math.radians(p.max_angular_dps), math.radians(p.angular_accel_dps2)
        dt = 1.0 / c.control_rate_hz
        tol = math.radians(c.yaw_tolerance_deg)
        w = 0.0
        sent: list[tuple[float, float]] = []  # (robot time, rate) of each command of this turn; at rest before
        while True:
            t_odo, odo = self._fresh(self._odom, p.odom)
            # Odometry is as old as its stamp (the sensor's latency, a loaded link): the base has since turned
            # by what the commands after that stamp asked for. Stopping on the stale heading alone overshot by
            # as much (stand-in odometry 0.3 s late: panorama views 7.6 degrees off their layout).
            ahead_rad = commanded_turn_rad(sent, t_odo, self.clock.now())
            err = float(wrap_angle(heading_rad - self._world(self._odom_pose(odo)).heading_rad - ahead_rad))
            if abs(err) <= tol:
                break
            # Speed that still stops in time (v^2 = 2 a d), P-control near the goal, then rate limits.
            want = math.copysign(min(w_max, math.sqrt(2 * a_max * abs(err)), c.turn_gain * abs(err) + 0.05), err)
            w = float(np.clip(want, w - a_max * dt, w + a_max * dt))
            self._send(0.0, w)
            sent.append((self.clock.now(), w))
            self._tick(end_s, "turn")
        self._send(0.0, 0.0)

    # --- Nav2 goals ----------------------------------------------------------------------------------------
    def _run_goal(self, client: ActionClient, goal: Any, end_s: float, what: str, on_tick=None) -> ClientGoal:
        """Send a goal and follow it to its end. Our deadline, a halt, the run-stop or a robot that
        fell silent cancel it (and raise); its feedback and odometry are read meanwhile."""
        c, p = self.config, self.profile
        try:
            handle = client.send_goal(goal, c.nav2_call_timeout_s)
        except ActionError as exc:
            raise NavigationFailedError(f"{what}: {exc}") from exc
        self.nav2_last_goal = handle
        try:
            while not handle.wait(0.05):
                self._check_safe()
                if self.clock.now() > end_s:
                    raise DeadlineExceededError(f"{what} (a Nav2 goal) did not finish within its deadline")
                self._fresh(self._odom, p.odom)  # the robot or the link is gone: cancel, do not wait
                if on_tick is not None:
                    on_tick(handle)
        except BaseException:
            self._cancel(client, handle, what)
            raise
        if on_tick is not None:
            on_tick(handle)
        return handle

    def _cancel(self, client: ActionClient, handle: ClientGoal, what: str) -> None:
        """Cancel a goal of ours and wait (bounded) to see it end; never raises (a cancel runs while
        another error is on its way up, and the zero Twists of ``_motion`` follow anyway)."""
        try:
            code = client.cancel(handle, self.config.nav2_cancel_wait_s)
            self.nav2_cancels += 1
            if not handle.wait(self.config.nav2_cancel_wait_s):
                log.warning("%s: the cancelled Nav2 goal did not report its end (cancel answered %s)", what, code.name)
        except Exception:
            log.exception("%s: could not cancel the Nav2 goal", what)

    def _goal_pose(self, xy, yaw_rad: float, z_m: float):
        """A PoseStamped in the frame our poses are in (the localisation's map frame, else odometry).
        Stamp zero: tf2 takes the newest transform, as for a goal clicked in RViz."""
        p = self.profile
        frame = p.map_frame or p.odom_frame
        pose = m.new("geometry_msgs/msg/Pose", position=m.new("geometry_msgs/msg/Point", x=float(xy[0]), y=float(xy[1]),
                                                             z=float(z_m)), orientation=m.quaternion_from_yaw(yaw_rad))
        return m.new("geometry_msgs/msg/PoseStamped", header=m.header(0.0, frame), pose=pose)

    @staticmethod
    def _result_code(handle: ClientGoal) -> tuple[int, str]:
        r = handle.result
        return (int(getattr(r, "error_code", 0)), str(getattr(r, "error_msg", ""))) if r is not None else (0, "")

    def _nav2_move(self, dx_m: float, dy_m: float, dist: float) -> MoveResult:
        p = self.profile
        with self._motion(self._deadline(dist, math.pi), "move_to") as end:
            start = self.pose
            target = np.array(start.position_m[:2]) + (dx_m, dy_m)
            goal = m.new("nav2_msgs/action/NavigateToPose_Goal",
                         pose=self._goal_pose(target, math.atan2(dy_m, dx_m), start.position_m[2]), behavior_tree="")
            odo0 = self._odom_pose(self._fresh(self._odom, p.odom)[1])
            track = {"xy": np.array(odo0.position_m[:2]), "travelled": 0.0}

            def on_tick(_h: ClientGoal) -> None:
                got = self._odom.get()
                xy = np.array(self._odom_pose(got[1]).position_m[:2])
                track["travelled"] += float(np.linalg.norm(xy - track["xy"]))  # on odometry, as cmd_vel's loop
                track["xy"] = xy

            handle = self._run_goal(self._nav, goal, end, "move_to", on_tick)
        code, why = self._result_code(handle)
        if handle.status == GoalStatus.SUCCEEDED:
            status = MoveStatus.REACHED
        elif handle.status == GoalStatus.ABORTED:
            outcome = nav2_outcome(code)
            if outcome == Nav2Outcome.TIMEOUT:
                raise DeadlineExceededError(f"move_to: Nav2 timed out (error {code}: {why})")
            if outcome == Nav2Outcome.FAULT:
                raise NavigationFailedError(f"move_to: Nav2 failed (error {code}: {why})")
            status = MoveStatus.UNREACHABLE if outcome == Nav2Outcome.UNREACHABLE else MoveStatus.BLOCKED
            log.info("move_to (%.2f, %.2f): Nav2 aborted, error %d %r: %s", dx_m, dy_m, code, why, status.value)
        elif handle.status == GoalStatus.CANCELED:
            raise GoalCanceledError("move_to: the Nav2 goal was cancelled by someone else")
        else:
            raise NavigationFailedError(f"move_to: the Nav2 goal ended {handle.status.name}")
        travelled = track["travelled"]
        return MoveResult(status=status, pose=self.pose, travelled_m=travelled,
                          steps=max(1, int(math.ceil(travelled / 0.25))) if travelled > 0 else 0)

    def _spin_by(self, angle_rad: float, end_s: float, what: str) -> None:
        """A Spin goal of ``angle_rad`` (relative, signed), its time allowance what is left of ours."""
        left_s = max(0.1, end_s - self.clock.now())
        goal = m.new("nav2_msgs/action/Spin_Goal", target_yaw=float(angle_rad), time_allowance=duration(left_s))
        handle = self._run_goal(self._spin, goal, end_s, what)
        if handle.status == GoalStatus.SUCCEEDED:
            return
        code, why = self._result_code(handle)
        if handle.status == GoalStatus.CANCELED:
            raise GoalCanceledError(f"{what}: the Spin goal was cancelled by someone else")
        outcome = nav2_outcome(code) if handle.status == GoalStatus.ABORTED else Nav2Outcome.FAULT
        if outcome == Nav2Outcome.TIMEOUT:
            raise DeadlineExceededError(f"{what}: Nav2's spin timed out (error {code}: {why})")
        if outcome == Nav2Outcome.BLOCKED:
            raise MotionBlockedError(f"{what}: Nav2's spin stopped (error {code}: {why})")
        raise NavigationFailedError(f"{what}: Nav2's spin ended {handle.status.name} (error {code}: {why})")

    def _turn_to(self, heading_rad: float, end_s: float, what: str) -> None:
        """To a heading: a Spin goal when Nav2 spins for us, else the cmd_vel loop."""
        if self._spin is None:
            self._rotate_to(heading_rad, end_s)
            return
        err = float(wrap_angle(heading_rad - self.pose.heading_rad))
        if abs(err) > math.radians(self.config.yaw_tolerance_deg):
            self._spin_by(err, end_s, what)

    def _settled_heading(self, since_s: float, end_s: float) -> float:
        """The heading in odometry stamped at or after ``since_s`` (robot time). Odometry that left the robot
        before it came to rest (sensor latency) still shows it turning, short of where it stopped."""
        while True:
            t, odo = self._fresh(self._odom, self.profile.odom)
            if t >= since_s:
                return float(self._world(self._odom_pose(odo)).heading_rad)
            self._tick(end_s, "settle")

    def _face(self, heading_rad: float, end_s: float, what: str, *, nav2_spin: bool) -> float:
        """Turn to a heading, settle, and return the heading the base came to rest at. The cmd_vel loop allows
        for its odometry's latency by its own commands; a base that did not follow them (acceleration limits,
        wheel slip, a controller stalled on a loaded machine) or a Nav2 spin can still stop past the
        tolerance. So the heading at rest is checked and the turn repeated, at most ``turn_corrections``
        times; whatever remains is reported as it is, never as the target."""
        c = self.config
        tol = math.radians(c.yaw_tolerance_deg)
        settled = heading_rad
        for _ in range(c.turn_corrections + 1):
            if nav2_spin:
                self._turn_to(heading_rad, end_s, what)
            else:
                self._rotate_to(heading_rad, end_s)
            self.clock.sleep(c.settle_s)
            settled = self._settled_heading(self.clock.now(), end_s)
            if abs(float(wrap_angle(heading_rad - settled))) <= tol:
                break
        return settled

    def turn(self, angle_rad: float) -> Pose:
        if not math.isfinite(angle_rad):
            raise ValueError("turn angle must be finite")
        if self._spin is not None:
            with self._motion(self._deadline(0.0, angle_rad), "turn") as end:
                # One goal, however long: Spin turns by its target (relative), not to a heading.
                if abs(angle_rad) > math.radians(self.config.yaw_tolerance_deg):
                    self._spin_by(angle_rad, end, "turn")
            return self.pose
        with self._motion(self._deadline(0.0, angle_rad), "turn") as end:
            start = self.pose.heading_rad
            # Long turns go in steps of at most 120 deg: wrap_angle would pick the short way round.
            n = max(1, int(math.ceil(abs(angle_rad) / math.radians(120))))
            for k in range(1, n + 1):
                self._rotate_to(start + angle_rad * k / n, end)
        return self.pose

    def _obstacle_ahead_m(self) -> float:
        """Nearest obstacle in the driving corridor (scan, else depth); inf when nothing is seen."""
        p = self.profile
        best = math.inf
        sc = self._scan.get()
        if sc is not None:
            s = sc[1]
            r = np.asarray(s.ranges, np.float64)
            a = s.angle_min + s.angle_increment * np.arange(len(r))
            ok = np.isfinite(r) & (r >= s.range_min) & (r <= s.range_max)
            x, y = r * np.cos(a), r * np.sin(a)
            corridor = ok & (x > 0) & (np.abs(y) <= p.base_radius_m + 0.05)
            if corridor.any():
                best = min(best, float(x[corridor].min()) - p.base_radius_m)
        dp = self._depth.get()
        if dp is not None and sc is None:
            d = self._depth_m(dp[1])
            h, w = d.shape
            band = d[h // 3: 2 * h // 3, w // 4: 3 * w // 4]
            v = band[band > 0]
            if v.size:
                best = min(best, float(np.percentile(v, 2)) - p.base_radius_m)
        return best

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult:
        if not (math.isfinite(dx_m) and math.isfinite(dy_m)):
            raise ValueError("move offset must be finite")
        dist = math.hypot(dx_m, dy_m)
        if dist < 1e-9:
            return MoveResult(status=MoveStatus.REACHED, pose=self.pose, travelled_m=0.0, steps=0)
        if self._nav is not None:
            return self._nav2_move(dx_m, dy_m, dist)
        c, p = self.config, self.profile
        with self._motion(self._deadline(dist, math.pi), "move_to") as end:
            start = self.pose
            target = np.array(start.position_m[:2]) + (dx_m, dy_m)
            self._rotate_to(math.atan2(dy_m, dx_m), end)
            dt = 1.0 / c.control_rate_hz
            v = 0.0
            travelled = 0.0  # on odometry: what the base drove, not the localisation's corrections
            last_xy = np.array(self._odom_pose(self._fresh(self._odom, p.odom)[1]).position_m[:2])
            best_rem, best_t = math.inf, self.clock.now()
            status = MoveStatus.BLOCKED
            while True:
                _, odo = self._fresh(self._odom, p.odom)
                odo_pose = self._odom_pose(odo)
                odo_xy = np.array(odo_pose.position_m[:2])
                travelled += float(np.linalg.norm(odo_xy - last_xy))
                last_xy = odo_xy
                pose = self._world(odo_pose)
                xy = np.array(pose.position_m[:2])
                rem_vec = target - xy
                rem = float(np.linalg.norm(rem_vec))
                if rem <= c.goal_tolerance_m:
                    status = MoveStatus.REACHED
                    break
                bearing = math.atan2(rem_vec[1], rem_vec[0])
                err = float(wrap_angle(bearing - pose.heading_rad))
                if abs(err) > math.pi / 2:  # overshot: the goal is behind
                    status = MoveStatus.REACHED if rem <= 2 * c.goal_tolerance_m else MoveStatus.BLOCKED
                    break
                clear = self._obstacle_ahead_m()
                if clear <= p.safety_distance_m:
                    status = MoveStatus.BLOCKED
                    break
                now = self.clock.now()
                if rem < best_rem - 0.01:
                    best_rem, best_t = rem, now
                elif now - best_t > c.stall_s:
                    status = MoveStatus.BLOCKED  # pushing without progress (a bump, a wall the scan missed)
                    break
                room = min(rem, clear - p.safety_distance_m)
                want = min(p.max_linear_mps, math.sqrt(2 * p.linear_accel_mps2 * max(room, 0.0)) + 0.02)
                want *= max(0.0, math.cos(err))
                v = float(np.clip(want, v - p.linear_accel_mps2 * dt, v + p.linear_accel_mps2 * dt))
                w = float(np.clip(c.turn_gain * err, -math.radians(p.max_angular_dps), math.radians(p.max_angular_dps)))
                self._send(v, w)
                self._tick(end, "move_to")
            self._send(0.0, 0.0)
        pose = self.pose
        step = 0.25
        return MoveResult(status=status, pose=pose, travelled_m=travelled, steps=max(1, int(math.ceil(travelled / step))))

    def reset(self, pose: Pose | None = None) -> Pose:
        if self._teleport is None:
            raise ResetUnsupportedError(f"profile {self.config.profile!r} has no teleport service: a real robot "
                                        "cannot be placed; drive it to the start instead")
        if pose is None:
            raise ResetUnsupportedError("a ROS 2 robot has no scene start pose: give the pose")
        self._send_zero()
        x, y, _ = pose.position_m
        try:
            self._teleport.call(m.new("turtlesim/srv/TeleportAbsolute_Request", x=float(x), y=float(y),
                                      theta=float(pose.heading_rad)), 10.0)
        except TransportError as exc:
            raise Ros2Error(f"teleport failed: {exc}") from exc
        # Wait for odometry that shows the new pose. "Stamped after the call" alone is not enough: the
        # clock we read can lag the odometry, so a message computed just before the teleport (the old
        # pose) may still be in flight with a newer stamp. Take the first newer odometry at the requested
        # pose; a simulator whose odometry frame is not the teleport's never matches, so after the link
        # has had time to drain its newest odometry is the answer.
        t0 = self.clock.now()
        end = time.monotonic() + 10.0
        settle_end = None
        while time.monotonic() < end:
            got = self._odom.get()
            if got and got[0] > t0:
                now = self._world(self._odom_pose(got[1]))
                if _same_place(now, pose):
                    return now
                settle_end = settle_end or time.monotonic() + TELEPORT_SETTLE_S
                if time.monotonic() > settle_end:
                    return now
            time.sleep(0.02)
        raise StaleDataError("no odometry after the teleport")

    # --- perception ---------------------------------------------------------------------------------------------
    def _depth_m(self, msg) -> np.ndarray:
        if hasattr(msg, "format"):  # a CompressedImage: compressed_depth_image_transport's layout
            return self._upright(m.compressed_depth_m(msg))
        a = m.image_array(msg)
        if msg.encoding in ("16UC1", "mono16"):
            d = a.astype(np.float32) * 0.001
        elif msg.encoding == "32FC1":
            d = np.where(np.isfinite(a), a, 0.0).astype(np.float32)
        else:
            raise m.CdrError(f"depth encoding {msg.encoding!r} is not 16UC1 or 32FC1")
        return self._upright(d)

    def _rgb(self, msg) -> np.ndarray:
        if hasattr(msg, "format"):
            return self._upright(m.compressed_rgb(msg))
        a = m.image_array(msg)
        if msg.encoding == "bgr8":
            a = a[..., ::-1]
        elif msg.encoding != "rgb8":
            raise m.CdrError(f"colour encoding {msg.encoding!r} is not rgb8, bgr8, jpeg or png")
        return self._upright(a)

    def _upright(self, a: np.ndarray) -> np.ndarray:
        k = self.profile.camera_rotation_quarters
        return np.ascontiguousarray(np.rot90(a, k)) if k else a

    def _intrinsics(self) -> np.ndarray:
        """The upright camera's K (camera_info is the sensor's own, before undoing the mounting)."""
        info = self._info.get()[1]
        k = np.asarray(info.k, np.float64).reshape(3, 3)
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        w, h = int(info.width), int(info.height)
        q = self.profile.camera_rotation_quarters
        for _ in range(q):  # np.rot90 (CCW): new x = y, new y = (w-1) - x
            fx, fy, cx, cy, w, h = fy, fx, cy, (w - 1) - cx, h, w
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])

    def _resample(self, img: np.ndarray, k_src: np.ndarray, cam: CameraIntrinsics, nearest: bool) -> np.ndarray:
        """The same view through the requested pinhole (same optical centre and axis): a homography."""
        k_dst = cam.pinhole()
        f = cam.width_px / 2.0 / math.tan(math.radians(cam.hfov_deg) / 2.0)
        kd = np.array([[f, 0, (cam.width_px - 1) / 2.0], [0, f, (cam.height_px - 1) / 2.0], [0, 0, 1]])
        h = k_src @ np.linalg.inv(kd)
        flags = (cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP
        del k_dst
        return cv2.warpPerspective(np.ascontiguousarray(img), h, (cam.width_px, cam.height_px), flags=flags,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _capture(self, after_s: float, cam: CameraIntrinsics, with_semantic: bool, deadline_s: float):
        """Colour stamped after ``after_s`` with the depth (and labels) of the same stamp."""
        p, c = self.profile, self.config
        while True:
            self._check_safe()
            if self.clock.now() > deadline_s:
                raise DeadlineExceededError("no camera frame after settling within the deadline")
            self._fresh(self._odom, p.odom)
            col = [x for x in self._color.all() if x[0] >= after_s]
            if col:
                t_c, cmsg = col[-1]
                dep = None
                if p.depth:
                    pairs = [x for x in self._depth.all() if abs(x[0] - t_c) <= c.stamp_match_s]
                    if not pairs:
                        self.clock.sleep(0.02)
                        continue
                    dep = min(pairs, key=lambda x: abs(x[0] - t_c))[1]
                sem = None
                if with_semantic and p.semantic:
                    # Labels of the same stamp: published after the colour, so they may still be on the way.
                    sp = [x for x in self._sem.all() if abs(x[0] - t_c) <= c.stamp_match_s]
                    if not sp:
                        self.clock.sleep(0.02)
                        continue
                    sem = min(sp, key=lambda x: abs(x[0] - t_c))[1]
                if self.clock.now() - t_c > c.max_data_age_s:
                    raise StaleDataError(f"{p.color} is stale ({self.clock.now() - t_c:.2f} s old)")
                k = self._intrinsics()
                rgb = self._resample(self._rgb(cmsg), k, cam, nearest=False)
                depth = (self._resample(self._depth_m(dep), k, cam, nearest=True) if dep is not None
                         else np.zeros((cam.height_px, cam.width_px), np.float32))
                labels = None
                if sem is not None:
                    raw = self._upright(m.image_array(sem).astype(np.int32))
                    labels = self._resample(raw + 1, k, cam, nearest=True).astype(np.int32) - 1  # border: -1
                return t_c, rgb, depth, labels
            self.clock.sleep(0.02)

    def observe(self, camera: CameraIntrinsics | None = None, with_semantic: bool = True) -> Panorama:
        cam = camera or self.config.camera
        c = self.config
        views = c.views
        with self._motion(self._deadline(0.0, 2 * math.pi) + views * (c.settle_s + 1.0), "observe") as end:
            start = self.pose
            targets = panorama_headings(start.heading_rad, views)
            rgbs, depths, sems, heads = [], [], [], []
            t_first = None
            for h in targets:
                heads.append(self._face(float(h), end, "observe", nav2_spin=False))
                t, rgb, depth, sem = self._capture(self.clock.now(), cam, with_semantic, end)
                t_first = t if t_first is None else t_first
                rgbs.append(rgb)
                depths.append(depth)
                sems.append(sem)
            self._face(start.heading_rad, end, "observe", nav2_spin=False)
        have_sem = with_semantic and all(s is not None for s in sems)
        # Reported headings are where each view looked (odometry at rest after the settle), not the
        # targets: the closed loop stops within yaw_tolerance_deg, short of the target in the turn's
        # direction, and the mapper's scan matching read that bias as a pose error (2-4 cm of
        # "correction" on a noise-free stand-in). Everything downstream takes each view's own heading.
        return Panorama(pose=start, camera=cam, headings_rad=np.asarray(heads, np.float64), rgb=np.stack(rgbs),
                        depth_m=np.stack(depths).astype(np.float32), semantic=np.stack(sems) if have_sem else None,
                        timestamp_s=float(t_first or 0.0), depth_noise_rel=self.profile.depth_noise_rel)

    def _frame(self, pitch_rad: float = 0.0) -> Frame | None:
        cam = self.config.camera
        got = self._color.get()
        if got is None or self._odom.get() is None:
            return None
        t_c, cmsg = got
        k = self._intrinsics()
        dep = None
        if self.profile.depth:
            pairs = [x for x in self._depth.all() if abs(x[0] - t_c) <= self.config.stamp_match_s]
            dep = min(pairs, key=lambda x: abs(x[0] - t_c))[1] if pairs else None
            if dep is None:
                # The newest colour's depth has not arrived yet: no frame now (a frame without depth from
                # a robot that has depth would fail the whole map build); the caller takes the next one.
                return None
        sem = None
        if self.profile.semantic:
            sp = [x for x in self._sem.all() if abs(x[0] - t_c) <= self.config.stamp_match_s]
            if sp:
                raw = self._upright(m.image_array(sp[-1][1]).astype(np.int32))
                sem = self._resample(raw + 1, k, cam, nearest=True).astype(np.int32) - 1
        imu = self._imu.get()
        pose = self._pose_at(t_c)
        with self._frame_lock:
            index = self._frame_index
            self._frame_index += 1
        frame = Frame(index=index, timestamp_s=t_c, pose=pose, pitch_rad=pitch_rad,
                      imu_heading_rad=float(m.yaw_from_quaternion(imu[1].orientation)) if imu else pose.heading_rad,
                      camera=cam, rgb=self._resample(self._rgb(cmsg), k, cam, nearest=False),
                      depth_m=None if dep is None else self._resample(self._depth_m(dep), k, cam, nearest=True),
                      semantic=sem, depth_noise_rel=0.0 if dep is None else self.profile.depth_noise_rel)
        return frame

    def _pose_at(self, t_s: float) -> Pose:
        return self.pose  # the newest (localised) odometry; at 20+ Hz it is within one period of the image

    def look_around(self) -> list[Frame]:
        """Yaw sweep 0 -> +60 -> -60 -> 0 with the base (the head's tilt is not driven): a frame per step."""
        c = self.config
        frames: list[Frame] = []
        with self._motion(self._deadline(0.0, math.radians(240)) + 30.0, "look_around") as end:
            h0 = self.pose.heading_rad
            step = math.radians(c.look_step_deg)
            path = [0.0]
            for a, b in ((0.0, math.radians(60)), (math.radians(60), -math.radians(60)), (-math.radians(60), 0.0)):
                n = max(1, int(round(abs(b - a) / step)))
                path += [a + (b - a) * k / n for k in range(1, n + 1)]
            for yaw in path:
                self._face(h0 + yaw, end, "look_around", nav2_spin=True)
                t0 = self.clock.now()
                self._capture(t0, c.camera, True, end)  # waits for a frame taken after settling
                f = self._frame()
                while f is None and self.clock.now() < end:  # a newer colour whose depth is on its way
                    self.clock.sleep(0.02)
                    f = self._frame()
                if f is not None:
                    frames.append(f)
                    for sink, _ in self._sinks:
                        sink(f)
        return frames

    @contextlib.contextmanager
    def recording(self, sink: FrameSink, rate_hz: float = 10.0) -> Iterator[None]:
        """Frames at ``rate_hz`` of robot time from the newest colour/depth, odometry and IMU."""
        if not rate_hz > 0:
            raise RobotIOError(f"rate_hz must be positive, got {rate_hz}")
        stop = threading.Event()
        entry = (sink, float(rate_hz))

        def run():
            last_stamp = None
            while not stop.is_set():
                try:
                    got = self._color.get()
                    if got is not None and got[0] != last_stamp:
                        f = self._frame()
                        if f is not None:
                            last_stamp = got[0]
                            sink(f)
                except Exception:
                    log.exception("recording frame failed")
                self.clock.sleep(1.0 / rate_hz)

        th = threading.Thread(target=run, name="ros2-recording", daemon=True)
        self._sinks.append(entry)
        th.start()
        try:
            yield
        finally:
            stop.set()
            th.join(5.0)
            self._sinks.remove(entry)

    # --- maps --------------------------------------------------------------------------------------------------
    def _grid(self):
        got = self._map.get()
        if got is None:
            raise NotImplementedError(f"no {self.profile.map or 'map topic'} published: no geodesic queries")
        if self._map_cache is None or self._map_cache[0] != got[0]:
            from libs.ros2.occupancy import OccupancyPlanner

            self._map_cache = (got[0], OccupancyPlanner.from_msg(got[1], self.profile.base_radius_m))
        return self._map_cache[1]

    def geodesic_distance(self, start_m, goal_m) -> float:
        return self._grid().distance(start_m, goal_m)

    def shortest_path(self, start_m, goal_m) -> np.ndarray | None:
        return self._grid().path(start_m, goal_m)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for _ in range(3):
            self._send_zero()
        time.sleep(0.05)  # let the zero Twists leave before the session goes
        for client in (getattr(self, "_nav", None), getattr(self, "_spin", None)):
            if client is not None:
                client.close()
        self.node.close()
        if self._owns_transport:
            self.transport.close()
