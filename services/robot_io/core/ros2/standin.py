"""A ROS 2 stand-in of the embedded simulator: a robot that speaks only ROS 2 messages.

It subscribes to ``cmd_vel`` and integrates it at a fixed control rate in simulated time, with
collisions against the scene (the simulator's navigation grid); it publishes colour, depth,
camera_info, odometry, scan, IMU, tf, the clock and the map with stamps, as the profile names them;
it answers the Trigger (navigation mode) and teleport services. Whatever works against it works
against the robot, because the backend sees nothing but the ROS 2 messages.

Time: simulated time advances one control period per tick; ``time_scale`` ticks that many times
faster than real time (tests); stamps are ``epoch + simulated time`` and the clock topic carries them.
Faults for tests: odometry drift (the simulator's noise model), latency, dropped messages. With the
profile's ``map_frame`` it localises as well: a perfect ``map -> odom`` transform on ``tf`` beside
``odom -> base``, the one that takes the drifting odometry to the true pose.

Nav2 (``nav2_actions``): it serves the profile's NavigateToPose action as bt_navigator does - plan on
the navigation grid, follow the path under the profile's limits, feedback (pose, distance remaining,
navigation time), CANCELED on a cancel request, ABORTED with Nav2's planner error codes when there is
no path (GOAL_OCCUPIED, NO_VALID_PATH) and the controller's FAILED_TO_MAKE_PROGRESS when the base
stops making progress - and the Spin behaviour. While a goal runs, its controller drives the base and
cmd_vel from elsewhere is ignored (Nav2's controller_server owns cmd_vel then).
"""

from __future__ import annotations

import heapq
import logging
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from shared.geometry import planar_between, wrap_angle
from shared.registry import BackendConfig
from shared.schemas import CameraIntrinsics, Pose

from shared.geometry import planar_apply

from libs.ros2 import messages as m
from libs.ros2.action import ActionServer, GoalStatus, ServerGoal, duration, duration_s
from libs.ros2.keys import KeyStyle, Qos
from libs.ros2.node import Ros2Node
from libs.ros2.profiles import ColorEncoding, DepthEncoding, Ros2Profile
from libs.ros2.transport import Ros2Transport

from ..robot import SimConfig, SimRobot
from ..sensors import SensorNoiseConfig

log = logging.getLogger(__name__)


class StandInConfig(BackendConfig):
    scene: str = "generated:0"
    scenes_dir: str | None = None
    camera: CameraIntrinsics = Field(default_factory=CameraIntrinsics)  # upright camera, before mounting
    time_scale: float = Field(1.0, gt=0.0, le=100.0)
    control_rate_hz: float = Field(30.0, ge=1.0, le=500.0)
    camera_rate_hz: float = Field(5.0, gt=0.0, le=60.0)
    scan_rate_hz: float = Field(10.0, gt=0.0, le=60.0)
    map_period_s: float = Field(5.0, gt=0.0)
    scan_beams: int = Field(360, ge=8, le=4096)
    scan_range_max_m: float = Field(8.0, gt=0.1, le=100.0)
    scan_height_m: float = Field(0.25, ge=0.0, le=2.0)
    cmd_timeout_s: float = Field(0.5, gt=0.0, le=10.0)  # a base stops when commands stop (driver watchdog)
    latency_s: float = Field(0.0, ge=0.0, le=10.0)  # sensor messages are published this much later
    drop_fraction: float = Field(0.0, ge=0.0, lt=1.0)  # sensor messages dropped at random
    noise: SensorNoiseConfig = Field(default_factory=SensorNoiseConfig)
    seed: int = 0
    start_pose: Pose | None = None
    hardware_max_linear_mps: float = Field(1.0, gt=0.0)
    hardware_max_angular_rps: float = Field(2.0, gt=0.0)
    node_name: str = "standin_robot"
    # Nav2's actions (bt_navigator's NavigateToPose, behavior_server's Spin) under the profile's names.
    nav2_actions: bool = True
    planner_tolerance_m: float = Field(0.25, ge=0.0, le=2.0)  # NavFn's tolerance: a goal this near free space is planned to it
    xy_goal_tolerance_m: float = Field(0.05, gt=0.0, le=1.0)
    yaw_goal_tolerance_rad: float = Field(0.05, gt=0.0, le=1.0)
    progress_timeout_s: float = Field(10.0, gt=0.0, le=120.0)  # Nav2's progress checker: movement_time_allowance
    feedback_rate_hz: float = Field(10.0, gt=0.0, le=100.0)


# Nav2's error codes the stand-in reports (nav2_msgs ComputePathToPose / FollowPath / Spin results; Jazzy's
# bt_navigator puts the failing server's code into NavigateToPose's result).
NAV2_GOAL_OCCUPIED = 206
NAV2_NO_VALID_PATH = 208
NAV2_FAILED_TO_MAKE_PROGRESS = 105
NAV2_SPIN_TIMEOUT = 701


@dataclass
class _NavGoal:
    handle: ServerGoal
    path: np.ndarray  # (P, 3) in the true frame
    yaw_rad: float  # goal heading, true frame
    frame_id: str
    start_s: float
    goal_xyz: np.ndarray | None = None  # where the path ends, true frame (replans aim here)
    index: int = 0
    recoveries: int = 0
    best_rem_m: float = math.inf
    best_t_s: float = 0.0
    next_feedback_s: float = 0.0


@dataclass
class _SpinGoal:
    handle: ServerGoal
    target_rad: float  # signed, relative
    allowance_s: float  # 0: none
    start_s: float
    travelled_rad: float = 0.0
    next_feedback_s: float = 0.0


@dataclass
class StandInStats:
    ticks: int = 0
    cmd_received: int = 0
    nonzero_cmd: int = 0
    collisions: int = 0
    images: int = 0
    last_cmd: tuple[float, float] = (0.0, 0.0)
    nav2_goals: dict[str, int] = field(default_factory=dict)  # "<action> <STATUS>" -> goals ended so
    wall_per_tick_s: list[float] = field(default_factory=list)


class StandInRobot:
    """The stand-in; ``run()`` blocks until ``stop()``; ``step()`` advances one control period."""

    def __init__(self, config: StandInConfig, profile: Ros2Profile, transport: Ros2Transport, keys: KeyStyle):
        self.config, self.profile = config, profile
        self.sim = SimRobot(SimConfig(scene=config.scene, scenes_dir=config.scenes_dir, camera=config.camera,
                                      camera_height_m=profile.camera_height_m, agent_radius_m=profile.base_radius_m,
                                      noise=config.noise, start_pose=config.start_pose, render_threads=1))
        self.node = Ros2Node(transport, keys, config.node_name)
        self.rng = np.random.default_rng(config.seed)
        self.stats = StandInStats()
        self.epoch_s = time.time()
        self.t_s = 0.0
        self._pos = self.sim._pos.copy()
        self._heading = float(self.sim._heading)
        self._v, self._w = 0.0, 0.0
        self._cmd = (0.0, 0.0, -1e9)  # v, w, sim time received
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._delayed: list[tuple[float, int, object, object]] = []
        self._seq = 0
        p = profile
        self._pub_odom = self.node.publisher(p.odom, m.MESSAGES["odometry"])
        compressed = (ColorEncoding.JPEG, ColorEncoding.PNG)
        color_type = m.MESSAGES["compressed_image"] if p.color_encoding in compressed else m.MESSAGES["image"]
        self._pub_color = self.node.publisher(p.color, color_type, Qos(reliable=False, depth=1))
        self._pub_info = self.node.publisher(p.camera_info, m.MESSAGES["camera_info"])
        depth_type = (m.MESSAGES["compressed_image"] if p.depth_encoding == DepthEncoding.COMPRESSED_DEPTH
                      else m.MESSAGES["image"])
        self._pub_depth = self.node.publisher(p.depth, depth_type, Qos(reliable=False, depth=1)) if p.depth else None
        self._pub_sem = self.node.publisher(p.semantic, m.MESSAGES["image"], Qos(reliable=False, depth=1)) if p.semantic else None
        self._pub_scan = self.node.publisher(p.scan, m.MESSAGES["scan"]) if p.scan else None
        self._pub_imu = self.node.publisher(p.imu, m.MESSAGES["imu"]) if p.imu else None
        self._pub_tf = self.node.publisher(p.tf, m.MESSAGES["tf"]) if p.tf else None
        self._pub_clock = self.node.publisher(p.clock, m.MESSAGES["clock"]) if p.clock else None
        self._pub_map = self.node.publisher(p.map, m.MESSAGES["occupancy_grid"], Qos(transient_local=True, depth=1)) if p.map else None
        self._pub_runstop = self.node.publisher(p.run_stop, m.MESSAGES["bool"]) if p.run_stop else None
        self.run_stopped = False
        self.navigation_mode = False
        self.node.subscribe(p.cmd_vel, m.MESSAGES["twist"], self._on_cmd, max_queue=16)
        if p.nav_mode_service:
            self.node.serve(p.nav_mode_service, "std_srvs/srv/Trigger", self._on_nav_mode)
        if p.teleport_service:
            self.node.serve(p.teleport_service, "turtlesim/srv/TeleportAbsolute", self._on_teleport)
        self._motion_goal: _NavGoal | _SpinGoal | None = None
        self._bumped = False  # the last tick's motion hit an obstacle
        self._feedback: list[tuple[ServerGoal, object]] = []
        self._nav_server = self._spin_server = None
        if config.nav2_actions:
            self._nav_server = ActionServer(self.node, p.navigate_action, "nav2_msgs/action/NavigateToPose",
                                            on_goal=self._nav_goal_ok, on_accepted=self._nav_accepted,
                                            on_cancel=lambda _g: True, now_s=lambda: self.stamp_s)
            if p.spin_action:
                self._spin_server = ActionServer(self.node, p.spin_action, "nav2_msgs/action/Spin",
                                                 on_goal=self._spin_goal_ok, on_accepted=self._spin_accepted,
                                                 on_cancel=lambda _g: True, now_s=lambda: self.stamp_s)
        self._next_cam = 0.0
        self._next_scan = 0.0
        # The last camera render and scan ranges, keyed by the pose they were taken from: a base that
        # stands still (reconstructing, planning, a test between commands) would render the same
        # images at the camera rate for as long as it stands. Rendering is a pure function of the pose;
        # the noise (depth) is drawn per message after it, so every message is what it was before.
        self._view: tuple[bytes, object] | None = None
        self._ranges: tuple[bytes, np.ndarray] | None = None
        self._next_map = 0.0
        self._next_runstop = 0.0
        self._grid = self._occupancy() if p.map else None

    # --- ROS 2 inputs ----------------------------------------------------------------------------------
    def _on_cmd(self, msg, _info) -> None:
        v, w = float(msg.linear.x), float(msg.angular.z)
        if not (math.isfinite(v) and math.isfinite(w)):
            return  # a driver ignores a non-finite command
        c = self.config
        v = float(np.clip(v, -c.hardware_max_linear_mps, c.hardware_max_linear_mps))
        w = float(np.clip(w, -c.hardware_max_angular_rps, c.hardware_max_angular_rps))
        with self._lock:
            self._cmd = (v, w, self.t_s)
            self.stats.cmd_received += 1
            self.stats.last_cmd = (v, w)
            if v or w:
                self.stats.nonzero_cmd += 1

    def _on_nav_mode(self, _req):
        self.navigation_mode = True
        return m.trigger_response(True, "Now in navigation mode.")

    def _on_teleport(self, req):
        x, y, th = float(req.x), float(req.y), float(req.theta)
        if not all(map(math.isfinite, (x, y, th))):
            raise ValueError("non-finite teleport pose")
        with self._lock:
            # A teleport starts the odometry afresh: what it had drifted until now is only known here.
            dx, dy, dyaw = self.odometry_error()
            log.info("teleported; odometry was off the true pose by %.3f m, %.2f deg (odometry - true: "
                     "(%.3f, %.3f) m, %.2f deg)", math.hypot(dx, dy), abs(math.degrees(dyaw)), dx, dy,
                     math.degrees(dyaw))
            self._end_motion_goal(GoalStatus.ABORTED, 0, "the robot was teleported")
            self.sim.reset(Pose(position_m=(x, y, float(self._pos[2])), heading_rad=th))
            self._pos = self.sim._pos.copy()
            self._heading = float(self.sim._heading)
            self._v = self._w = 0.0
            self._cmd = (0.0, 0.0, -1e9)
        return m.new("turtlesim/srv/TeleportAbsolute_Response")

    # --- Nav2 actions -----------------------------------------------------------------------------------
    def _nav_goal_ok(self, goal) -> bool:
        p = goal.pose.pose
        return all(map(math.isfinite, (p.position.x, p.position.y, p.orientation.z, p.orientation.w)))

    def _spin_goal_ok(self, goal) -> bool:
        return math.isfinite(goal.target_yaw) and abs(goal.target_yaw) <= 4 * math.pi

    def _to_true(self, frame_id: str, xyz, yaw: float):
        """A pose in ``frame_id`` (the map frame is the true frame; the odometry frame drifts) in the true frame."""
        if self.profile.map_frame and frame_id.strip("/") == self.profile.map_frame.strip("/"):
            return np.asarray(xyz, np.float64), yaw
        odo, true = self.odometry_pose(), self.true_pose
        t_xyz, t_yaw = planar_between(odo.position_m, odo.heading_rad, true.position_m, true.heading_rad)
        out, h = planar_apply(t_xyz, t_yaw, xyz, yaw)
        return np.asarray(out, np.float64), h

    def _from_true(self, frame_id: str, xyz, yaw: float):
        if self.profile.map_frame and frame_id.strip("/") == self.profile.map_frame.strip("/"):
            return tuple(xyz), yaw
        odo, true = self.odometry_pose(), self.true_pose
        t_xyz, t_yaw = planar_between(true.position_m, true.heading_rad, odo.position_m, odo.heading_rad)
        return planar_apply(t_xyz, t_yaw, xyz, yaw)

    def _nav_accepted(self, handle: ServerGoal) -> None:
        """Plan as Nav2's planner server would (on the navigation grid, NavFn-like tolerance), then
        hand the path to the control loop; no path: ABORTED with the planner's error code."""
        c = self.config
        ps = handle.goal.pose
        frame = ps.header.frame_id or self.profile.odom_frame
        with self._lock:
            start = self._pos.copy()
            goal_xyz, goal_yaw = self._to_true(frame, (ps.pose.position.x, ps.pose.position.y, start[2]),
                                               m.yaw_from_quaternion(ps.pose.orientation))
        goal_xyz[2] = start[2]
        nav = self.sim.nav
        code, why, path = 0, "", None
        if not nav.is_navigable(goal_xyz):
            snapped = nav.snap(goal_xyz)
            if float(np.linalg.norm(snapped[:2] - goal_xyz[:2])) > c.planner_tolerance_m:
                code, why = NAV2_GOAL_OCCUPIED, f"goal ({goal_xyz[0]:.2f}, {goal_xyz[1]:.2f}) is in an obstacle"
            else:
                goal_xyz = snapped
        if not code:
            path = nav.shortest_path(start, goal_xyz)
            if path is None:
                code, why = NAV2_NO_VALID_PATH, "no path to the goal"
            else:
                # From the node the robot stands on: the path's segments are clear between node centres.
                path = np.vstack([path, goal_xyz[None]])
        if code:
            handle.execute()
            self._count_goal("navigate_to_pose", GoalStatus.ABORTED)
            handle.finish(GoalStatus.ABORTED, m.new("nav2_msgs/action/NavigateToPose_Result", error_code=code,
                                                    error_msg=why))
            return
        with self._lock:
            self._end_motion_goal(GoalStatus.ABORTED, 0, "preempted by a new goal")
            self._motion_goal = _NavGoal(handle, path, float(goal_yaw), frame, self.t_s, goal_xyz=goal_xyz,
                                         best_t_s=self.t_s)
        handle.execute()

    def _spin_accepted(self, handle: ServerGoal) -> None:
        g = handle.goal
        with self._lock:
            self._end_motion_goal(GoalStatus.ABORTED, 0, "preempted by a new goal")
            self._motion_goal = _SpinGoal(handle, float(g.target_yaw), duration_s(g.time_allowance), self.t_s)
        handle.execute()

    def _result(self, goal, code: int, why: str):
        if isinstance(goal, _SpinGoal):
            return m.new("nav2_msgs/action/Spin_Result", total_elapsed_time=duration(self.t_s - goal.start_s),
                         error_code=code, error_msg=why)
        return m.new("nav2_msgs/action/NavigateToPose_Result", error_code=code, error_msg=why)

    def _end_motion_goal(self, status: GoalStatus, code: int, why: str) -> None:
        """End the running goal (under ``_lock``)."""
        g, self._motion_goal = self._motion_goal, None
        if g is not None:
            self._count_goal("spin" if isinstance(g, _SpinGoal) else "navigate_to_pose", status)
            g.handle.finish(status, self._result(g, code, why))

    def _count_goal(self, action: str, status: GoalStatus) -> None:
        key = f"{action} {status.name}"
        self.stats.nav2_goals[key] = self.stats.nav2_goals.get(key, 0) + 1

    def _turn_rate(self, err: float) -> float:
        p = self.profile
        w_max, a_max = math.radians(p.max_angular_dps), math.radians(p.angular_accel_dps2)
        return math.copysign(min(w_max, math.sqrt(2 * a_max * abs(err)), 2.0 * abs(err) + 0.05), err)

    def _goal_control(self, dt: float) -> tuple[float, float] | None:
        """The running goal's command for this tick (under ``_lock``); None without a goal."""
        g = self._motion_goal
        if g is None:
            return None
        if g.handle.cancel_requested:
            self._end_motion_goal(GoalStatus.CANCELED, 0, "canceled")
            return 0.0, 0.0
        return self._spin_control(g, dt) if isinstance(g, _SpinGoal) else self._nav_control(g, dt)

    def _spin_control(self, g: _SpinGoal, dt: float) -> tuple[float, float]:
        rem = abs(g.target_rad) - g.travelled_rad
        if rem <= 1e-3:
            self._end_motion_goal(GoalStatus.SUCCEEDED, 0, "")
            return 0.0, 0.0
        if g.allowance_s > 0 and self.t_s - g.start_s > g.allowance_s:
            self._end_motion_goal(GoalStatus.ABORTED, NAV2_SPIN_TIMEOUT, "spin exceeded its time allowance")
            return 0.0, 0.0
        w = min(abs(self._turn_rate(rem)), rem / dt)  # the last tick lands on the target
        g.travelled_rad += w * dt
        if self.t_s >= g.next_feedback_s:
            g.next_feedback_s = self.t_s + 1.0 / self.config.feedback_rate_hz
            self._feedback.append((g.handle, m.new("nav2_msgs/action/Spin_Feedback",
                                                   angular_distance_traveled=float(g.travelled_rad))))
        return 0.0, math.copysign(w, g.target_rad)

    def _replan(self, g: _NavGoal) -> bool:
        """A recovery: the base touched an obstacle (it left the planned line at a corner), so plan
        again from where it is, as Nav2's replanning tree does. False: no path any more."""
        path = self.sim.nav.shortest_path(self._pos, g.goal_xyz)
        if path is None:
            return False
        g.path, g.index = np.vstack([path, g.goal_xyz[None]]), 0
        g.recoveries += 1
        return True

    def _nav_control(self, g: _NavGoal, dt: float) -> tuple[float, float]:
        c, p = self.config, self.profile
        if self._bumped:
            self._bumped = False
            if not self._replan(g):
                self._end_motion_goal(GoalStatus.ABORTED, NAV2_NO_VALID_PATH, "no path from here any more")
                return 0.0, 0.0
        pos, heading = self._pos[:2], self._heading
        last = len(g.path) - 1
        # Waypoint by waypoint, each one reached (the last tick lands on it): the segments between
        # them are the clear ones, and cutting a corner would touch the wall beside it.
        while g.index < last and np.linalg.norm(g.path[g.index, :2] - pos) < 1e-3:
            g.index += 1
        tgt = g.path[g.index, :2]
        d = float(np.linalg.norm(tgt - pos))
        rem = d + float(np.linalg.norm(np.diff(g.path[g.index:, :2], axis=0), axis=1).sum())
        if rem < g.best_rem_m - 0.02:
            g.best_rem_m, g.best_t_s = rem, self.t_s
        if self.t_s >= g.next_feedback_s:
            g.next_feedback_s = self.t_s + 1.0 / c.feedback_rate_hz
            xyz, yaw = self._from_true(g.frame_id, tuple(self._pos), heading)
            pose = m.new("geometry_msgs/msg/PoseStamped", header=m.header(self.stamp_s, g.frame_id), pose=m.new(
                "geometry_msgs/msg/Pose", position=m.new("geometry_msgs/msg/Point", x=float(xyz[0]), y=float(xyz[1]),
                                                         z=float(xyz[2])), orientation=m.quaternion_from_yaw(yaw)))
            self._feedback.append((g.handle, m.new(
                "nav2_msgs/action/NavigateToPose_Feedback", current_pose=pose,
                navigation_time=duration(self.t_s - g.start_s),
                estimated_time_remaining=duration(rem / p.max_linear_mps), number_of_recoveries=g.recoveries,
                distance_remaining=float(rem))))
        if g.index == last and d <= c.xy_goal_tolerance_m:
            err = float(wrap_angle(g.yaw_rad - heading))
            if abs(err) <= c.yaw_goal_tolerance_rad:
                self._end_motion_goal(GoalStatus.SUCCEEDED, 0, "")
                return 0.0, 0.0
            return 0.0, math.copysign(min(abs(self._turn_rate(err)), abs(err) / dt), err)
        if self.t_s - g.best_t_s > c.progress_timeout_s:
            self._end_motion_goal(GoalStatus.ABORTED, NAV2_FAILED_TO_MAKE_PROGRESS,
                                  f"no progress for {c.progress_timeout_s:.0f} s")
            return 0.0, 0.0
        err = float(wrap_angle(math.atan2(tgt[1] - pos[1], tgt[0] - pos[0]) - heading))
        w_max = math.radians(p.max_angular_dps)
        if abs(err) > 0.05 and d > 1e-3:  # face the segment first (a differential base turns in place)
            return 0.0, math.copysign(min(abs(self._turn_rate(err)), abs(err) / dt), err)
        # On the segment's bearing exactly (the heading turns before the step): a tracking
        # controller's error is centimetres, and a centimetre past a cell edge is a bump here.
        v = min(p.max_linear_mps, math.sqrt(2 * p.linear_accel_mps2 * rem) + 0.02, d / dt) * math.cos(err)
        return v, float(np.clip(err / dt, -w_max, w_max))

    def _publish_feedback(self) -> None:
        with self._lock:
            pending, self._feedback = self._feedback, []
        for handle, fb in pending:
            handle.publish_feedback(fb)

    # --- simulation ------------------------------------------------------------------------------------
    @property
    def stamp_s(self) -> float:
        return self.epoch_s + self.t_s

    @property
    def true_pose(self) -> Pose:
        return Pose(position_m=tuple(float(v) for v in self._pos), heading_rad=self._heading)

    def step(self) -> None:
        """One control period: integrate the command (with collisions), publish what is due."""
        c, p = self.config, self.profile
        dt = 1.0 / c.control_rate_hz
        with self._lock:
            v_cmd, w_cmd, t_cmd = self._cmd
            if self.t_s - t_cmd > c.cmd_timeout_s or self.run_stopped:
                v_cmd = w_cmd = 0.0
            if self.run_stopped:
                self._end_motion_goal(GoalStatus.ABORTED, 0, "run-stopped")
            goal_cmd = self._goal_control(dt)
            if goal_cmd is not None:
                v_cmd, w_cmd = goal_cmd
            self._v, self._w = v_cmd, w_cmd
            self._heading = float(wrap_angle(self._heading + w_cmd * dt))
            moved = 0.0
            if abs(v_cmd) > 1e-9:
                d = v_cmd * dt
                goal = self._pos + np.array([math.cos(self._heading) * d, math.sin(self._heading) * d, 0.0])
                end, ok = self.sim.nav.walk(self._pos, goal)
                if not ok:
                    self.stats.collisions += 1
                    self._v = 0.0
                    self._bumped = True
                moved = float(np.linalg.norm(end[:2] - self._pos[:2]))
                self._pos = np.asarray(end, np.float64)
            self.sim.noise.on_motion(moved, abs(w_cmd) * dt)
            self.t_s += dt
            self.stats.ticks += 1
        self._publish_feedback()
        self._publish_state()

    def _sensor(self, pub, msg) -> None:
        """A sensor message: maybe dropped, maybe delayed (faults), else published now."""
        c = self.config
        if c.drop_fraction and self.rng.random() < c.drop_fraction:
            return
        if c.latency_s > 0:
            self._seq += 1
            heapq.heappush(self._delayed, (self.t_s + c.latency_s, self._seq, pub, msg))
            return
        pub.publish(msg)

    def _flush_delayed(self) -> None:
        while self._delayed and self._delayed[0][0] <= self.t_s:
            _, _, pub, msg = heapq.heappop(self._delayed)
            pub.publish(msg)

    def odometry_pose(self) -> Pose:
        return self.sim.noise.odometry(self.true_pose)

    def odometry_error(self) -> tuple[float, float, float]:
        """Odometry minus the true pose: (dx m, dy m, dyaw rad in [-pi, pi]); only the stand-in knows it."""
        odo, true = self.odometry_pose(), self.true_pose
        return (odo.position_m[0] - true.position_m[0], odo.position_m[1] - true.position_m[1],
                math.remainder(odo.heading_rad - true.heading_rad, 2 * math.pi))

    def _map_from_odom(self, t: float, true: Pose, odo: Pose):
        """A perfect localiser's map -> odom transform: the one that takes the (drifting) odometry
        pose to the true pose, as AMCL or slam_toolbox estimate it on a robot."""
        xyz, yaw = planar_between(odo.position_m, odo.heading_rad, true.position_m, true.heading_rad)
        return m.transform_stamped(t, self.profile.map_frame, self.profile.odom_frame, xyz, yaw)

    def _publish_state(self) -> None:
        p, c = self.profile, self.config
        with self._lock:  # a stamp and a pose of the same instant: a teleport cannot fall between them
            t, odo, true = self.stamp_s, self.odometry_pose(), self.true_pose
        if self._pub_clock:
            self._pub_clock.publish(m.clock(t))
        self._sensor(self._pub_odom, m.odometry(t, odo.position_m, odo.heading_rad, self._v, self._w, p.odom_frame, p.base_frame))
        if self._pub_tf:
            tfs = [m.transform_stamped(t, p.odom_frame, p.base_frame, odo.position_m, odo.heading_rad)]
            if p.map_frame:
                tfs.append(self._map_from_odom(t, true, odo))
            self._pub_tf.publish(m.tf_message(tfs))
        if self._pub_imu:
            self._sensor(self._pub_imu, m.imu(t, "imu", self.sim.noise.imu_heading(self._heading), self._w))
        if self._pub_scan and self.t_s >= self._next_scan:
            self._next_scan = max(self._next_scan + 1.0 / c.scan_rate_hz, self.t_s - 0.5 / c.scan_rate_hz)
            self._sensor(self._pub_scan, self._scan(t))
        if self.t_s >= self._next_cam:
            # On the rate's own grid: due times rounded up to ticks would slow the camera down.
            self._next_cam = max(self._next_cam + 1.0 / c.camera_rate_hz, self.t_s - 0.5 / c.camera_rate_hz)
            self._publish_camera(t)
        if self._pub_map and self.t_s >= self._next_map:
            self._next_map = self.t_s + c.map_period_s
            grid, res, origin = self._grid
            self._pub_map.publish(m.occupancy_grid(t, p.map_frame or "map", grid, res, origin))
        if self._pub_runstop and self.t_s >= self._next_runstop:
            self._next_runstop = self.t_s + 1.0
            self._pub_runstop.publish(m.boolean(self.run_stopped))
        self._flush_delayed()

    def _pose_key(self) -> bytes:
        return self._pos.tobytes() + np.float64(self._heading).tobytes()

    def _render(self):
        """The camera's view from the current pose (rendered again only when the pose has changed)."""
        key = self._pose_key()
        if self._view is None or self._view[0] != key:
            p, cam = self.profile, self.config.camera
            out = self.sim.renderer.render_views(self._pos, np.array([self._heading]), cam.pinhole(), 0.0,
                                                 p.camera_height_m, with_semantic=p.semantic is not None)
            self._view = (key, out)
        return self._view[1]

    def _publish_camera(self, t: float) -> None:
        p, cam = self.profile, self.config.camera
        out = self._render()
        k = p.camera_rotation_quarters
        # The mounting rotates what the sensor sees: undo "upright" by the inverse quarter turns.
        rot = (lambda a: np.ascontiguousarray(np.rot90(a, -k))) if k else (lambda a: a)
        rgb = rot(out.rgb[0])
        if p.color_encoding in (ColorEncoding.JPEG, ColorEncoding.PNG):
            color = m.compressed_image(t, p.camera_frame, rgb, fmt=str(p.color_encoding))
        elif p.color_encoding == ColorEncoding.BGR8:
            color = m.image(t, p.camera_frame, rgb[..., ::-1], "bgr8")
        else:
            color = m.image(t, p.camera_frame, rgb, "rgb8")
        f = cam.width_px / 2.0 / math.tan(math.radians(cam.hfov_deg) / 2.0)
        w, h = cam.width_px, cam.height_px
        cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
        if k % 2:  # the sensor's own image is portrait: its intrinsics are the rotated ones
            w, h, cx, cy = h, w, cy, cx
        self._sensor(self._pub_info, m.camera_info(t, p.camera_frame, w, h, f, f, cx, cy))
        self._sensor(self._pub_color, color)
        if self._pub_depth is not None:
            d = np.where(np.isfinite(out.depth_m[0]), out.depth_m[0], 0.0).astype(np.float32)
            d = self.sim.noise.depth(d)
            if p.depth_encoding in (DepthEncoding.MM_16UC1, DepthEncoding.COMPRESSED_DEPTH):
                mm = rot(np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16))
                img = (m.compressed_depth(t, p.camera_frame, mm) if p.depth_encoding == DepthEncoding.COMPRESSED_DEPTH
                       else m.image(t, p.camera_frame, mm, "16UC1"))
            else:
                img = m.image(t, p.camera_frame, rot(d), "32FC1")
            self._sensor(self._pub_depth, img)
        if self._pub_sem is not None and out.semantic is not None:
            self._sensor(self._pub_sem, m.image(t, p.camera_frame, rot(out.semantic[0].astype(np.int32)), "32SC1"))
        self.stats.images += 1

    def _scan(self, t: float):
        c = self.config
        n = c.scan_beams
        inc = 2 * math.pi / n
        ang = -math.pi + inc * np.arange(n)
        key = self._pose_key()
        if self._ranges is None or self._ranges[0] != key:  # as the camera: cast again only after a move
            world = self._heading + ang
            dirs = np.stack([np.cos(world), np.sin(world), np.zeros(n)], axis=1)
            origin = self._pos + np.array([0.0, 0.0, c.scan_height_m])
            r = np.asarray(self.sim.renderer.first_hit_distance(origin, dirs), np.float64)
            self._ranges = (key, np.where(r > c.scan_range_max_m, np.inf, r).astype(np.float32))
        r = self._ranges[1]
        return m.laser_scan(t, "laser", r, -math.pi, inc, 0.05, c.scan_range_max_m, 1.0 / c.scan_rate_hz)

    def _occupancy(self):
        """A 2D occupancy grid of the floor the robot starts on, from the navigation grid."""
        nav = self.sim.nav
        nodes = nav.nodes_m
        z0 = float(self._pos[2])
        on_floor = np.abs(nodes[:, 2] - z0) < 0.3
        pts = nodes[on_floor & (nav.component == nav.main_component)]
        res = float(nav.cell_m)
        lo = pts[:, :2].min(axis=0) - 1.0
        hi = pts[:, :2].max(axis=0) + 1.0
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1)
        grid = np.full((h, w), 100, np.int8)
        ij = np.floor((pts[:, :2] - lo) / res).astype(int)
        free = np.zeros((h, w), bool)
        free[ij[:, 1], ij[:, 0]] = True
        # Navigation-grid nodes are where the agent's centre fits; a map shows the floor itself.
        from scipy.ndimage import binary_dilation

        r = max(1, int(round(self.sim.agent.radius_m / res)))
        free = binary_dilation(free, iterations=r)
        grid[free] = 0
        return grid, res, (float(lo[0]), float(lo[1]))

    # --- running ---------------------------------------------------------------------------------------
    def run(self) -> None:
        """Tick at the control rate, ``time_scale`` times faster than real time, until ``stop``."""
        period = 1.0 / (self.config.control_rate_hz * self.config.time_scale)
        nxt = time.monotonic()
        while not self._stop.is_set():
            t0 = time.monotonic()
            self.step()
            dt = time.monotonic() - t0
            if len(self.stats.wall_per_tick_s) < 100_000:
                self.stats.wall_per_tick_s.append(dt)
            nxt += period
            delay = nxt - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                nxt = time.monotonic()  # behind (rendering): simulated time slows, it never skips

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self.stop()
        for server in (self._nav_server, self._spin_server):
            if server is not None:
                server.close()  # releases the get_result queries waiting on a goal
        self.node.close()
        self.sim.close()
