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

from libs.ros2 import messages as m
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


@dataclass
class StandInStats:
    ticks: int = 0
    cmd_received: int = 0
    nonzero_cmd: int = 0
    collisions: int = 0
    images: int = 0
    last_cmd: tuple[float, float] = (0.0, 0.0)
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
        self._next_cam = 0.0
        self._next_scan = 0.0
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
            self.sim.reset(Pose(position_m=(x, y, float(self._pos[2])), heading_rad=th))
            self._pos = self.sim._pos.copy()
            self._heading = float(self.sim._heading)
            self._v = self._w = 0.0
            self._cmd = (0.0, 0.0, -1e9)
        return m.new("turtlesim/srv/TeleportAbsolute_Response")

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
                moved = float(np.linalg.norm(end[:2] - self._pos[:2]))
                self._pos = np.asarray(end, np.float64)
            self.sim.noise.on_motion(moved, abs(w_cmd) * dt)
            self.t_s += dt
            self.stats.ticks += 1
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

    def _publish_camera(self, t: float) -> None:
        p, cam = self.profile, self.config.camera
        out = self.sim.renderer.render_views(self._pos, np.array([self._heading]), cam.pinhole(), 0.0,
                                             p.camera_height_m, with_semantic=p.semantic is not None)
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
        world = self._heading + ang
        dirs = np.stack([np.cos(world), np.sin(world), np.zeros(n)], axis=1)
        origin = self._pos + np.array([0.0, 0.0, c.scan_height_m])
        r = np.asarray(self.sim.renderer.first_hit_distance(origin, dirs), np.float64)
        r = np.where(r > c.scan_range_max_m, np.inf, r).astype(np.float32)
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
        self.node.close()
        self.sim.close()
