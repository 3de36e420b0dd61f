"""Robot profiles: which ROS 2 topics, encodings, frames, services and limits a robot has. Data only.

The ``ros2`` backend and the stand-in robot both read a profile, so the stand-in publishes exactly
what the backend expects from the real robot. A profile is chosen by name and may be overridden
field by field from config (``{"profile": "generic", "profile_overrides": {"odom": "/wheel/odom"}}``).
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from pydantic import Field, field_validator, model_validator

from shared.registry import BackendConfig
from shared.schemas import DepthNoiseRel

from .errors import Ros2ProtocolError


class ColorEncoding(StrEnum):
    RGB8 = "rgb8"
    BGR8 = "bgr8"
    JPEG = "jpeg"  # sensor_msgs/CompressedImage (image_transport "compressed", jpeg)
    PNG = "png"  # sensor_msgs/CompressedImage (image_transport "compressed", png: lossless)


class DepthEncoding(StrEnum):
    MM_16UC1 = "16UC1"  # millimetres (RealSense, Stretch)
    M_32FC1 = "32FC1"  # metres
    # sensor_msgs/CompressedImage as compressed_depth_image_transport publishes 16UC1 millimetres:
    # a 12-byte ConfigHeader (int32 format, float32 depthParam[2]) then a 16-bit PNG.
    COMPRESSED_DEPTH = "compressedDepth"


class Motion(StrEnum):
    """How the backend moves the base."""

    CMDVEL = "cmdvel"  # its own closed loop on odometry, publishing cmd_vel (any base)
    NAV2 = "nav2"  # goals to the robot's Nav2: NavigateToPose (bt_navigator), Spin (behavior_server)


class Ros2Profile(BackendConfig):
    """Topic names (absolute, or relative to the namespace), encodings, frames, services and limits.

    A topic set to ``None`` is absent on this robot (no depth: views without depth; no scan: depth
    alone guards motion; no map: geodesic queries are NotImplemented; no clock: wall time)."""

    description: str = ""
    cmd_vel: str = "/cmd_vel"
    odom: str = "/odom"
    color: str = "/camera/color/image_raw"
    color_encoding: ColorEncoding = ColorEncoding.RGB8
    camera_info: str = "/camera/color/camera_info"
    depth: str | None = "/camera/depth/image_raw"
    depth_encoding: DepthEncoding = DepthEncoding.M_32FC1
    semantic: str | None = None  # 32SC1 class ids (simulators); real cameras have none
    scan: str | None = "/scan"
    imu: str | None = None
    map: str | None = None  # nav_msgs/OccupancyGrid
    tf: str | None = "/tf"
    clock: str | None = None  # rosgraph_msgs/Clock (use_sim_time); None: stamps are wall time
    run_stop: str | None = None  # std_msgs/Bool, true while the run-stop is pressed
    nav_mode_service: str | None = None  # std_srvs/Trigger called once on connect
    teleport_service: str | None = None  # turtlesim/TeleportAbsolute (simulators only)
    # ``nav2``: move_to sends NavigateToPose goals (Nav2's planner, costmaps, controller and recoveries
    # drive the base), turn and look_around Spin goals; ``cmdvel`` where an action server does not
    # answer. Observe keeps the cmd_vel loop: its 12 headings need 1.5 degree accuracy.
    motion: Motion = Motion.CMDVEL
    navigate_action: str = "/navigate_to_pose"  # nav2 bt_navigator's action (nav2_msgs/action/NavigateToPose)
    spin_action: str | None = "/spin"  # nav2 behavior_server's spin behaviour (nav2_msgs/action/Spin)
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    # The frame of the robot's localisation (nav2's AMCL or slam_toolbox publish ``map_frame ->
    # odom_frame`` on ``tf``). With it, every pose the backend reports (frames, panoramas, moves) is
    # the odometry composed with the newest map -> odom transform: a map built over a long
    # exploration does not carry the odometry's drift, and poses agree with the map topic's grid,
    # which is in this frame. None: odometry is the world frame (a robot without localisation).
    map_frame: str | None = None
    camera_frame: str = "camera_color_optical_frame"
    # The camera's mounting roll, in quarter turns counter-clockwise of the image as it arrives
    # relative to upright (Stretch's head D435i is mounted on its side: its images arrive rotated).
    camera_rotation_quarters: int = Field(0, ge=0, le=3)
    camera_height_m: float = Field(1.25, gt=0.0, le=3.0)
    # The depth camera's error, sigma = depth_noise_rel * depth^2 (0: not known): carried by every
    # frame, so that the reconstructor fuses depth only as far as it is good (``Frame.depth_noise_rel``).
    # A stereo camera's is subpixel / (focal_px * baseline_m): a D435 at 848 px (~420 px focal, 50 mm,
    # 0.08 px) ~0.004, i.e. 4 cm at 3.2 m.
    depth_noise_rel: DepthNoiseRel = 0.0
    max_linear_mps: float = Field(0.3, gt=0.0, le=2.0)
    max_angular_dps: float = Field(45.0, gt=0.0, le=360.0)
    linear_accel_mps2: float = Field(0.5, gt=0.0, le=10.0)
    angular_accel_dps2: float = Field(120.0, gt=0.0, le=2000.0)
    safety_distance_m: float = Field(0.3, ge=0.05, le=3.0)
    base_radius_m: float = Field(0.17, gt=0.0, le=1.0)

    @field_validator("cmd_vel", "odom", "color", "camera_info", "navigate_action")
    @classmethod
    def _required(cls, v: str) -> str:
        if not v or not v.strip("/"):
            raise ValueError("this topic is required")
        return v

    @model_validator(mode="after")
    def _localisation(self) -> Ros2Profile:
        if self.map_frame is not None:
            if not self.map_frame.strip("/") or self.map_frame.strip("/") == self.odom_frame.strip("/"):
                raise ValueError(f"map_frame must name a frame other than odom_frame {self.odom_frame!r}")
            if not self.tf:
                raise ValueError("map_frame needs the tf topic: the map -> odom transform arrives on it")
        return self


PROFILES: dict[str, Ros2Profile] = {
    "stretch": Ros2Profile(
        description="Hello Robot Stretch (stretch_ros2 driver in navigation mode, D435i head camera, RPLidar)",
        cmd_vel="/stretch/cmd_vel",
        odom="/odom",
        color="/camera/color/image_raw",
        camera_info="/camera/color/camera_info",
        depth="/camera/aligned_depth_to_color/image_raw",
        depth_encoding=DepthEncoding.MM_16UC1,
        scan="/scan",
        imu="/imu_mobile_base",
        map="/map",
        run_stop="/is_runstopped",
        map_frame="map",  # /map comes with localisation (nav2 AMCL or slam_toolbox) publishing map -> odom
        nav_mode_service="/switch_to_navigation_mode",
        camera_rotation_quarters=1,
        camera_height_m=1.29,
        depth_noise_rel=0.004,
        max_linear_mps=0.3,
        max_angular_dps=45.0,
        safety_distance_m=0.3,
        base_radius_m=0.17,
    ),
    "generic": Ros2Profile(description="any ROS 2 base: every topic, encoding and frame configurable"),
}

# What the stand-in robot (services/robot_io/tools/ros2_robot.py) publishes beyond the generic profile,
# and a backend driving it therefore reads: the simulated clock (time scale), the teleport service
# (mission start poses), the map and labels. The base is the embedded simulator's agent (radius 0.1 m,
# which VLN-CE's graphs and tours assume) with a small safety margin, and it may turn faster than a
# Stretch: panoramas take less (simulated) time. The launcher runs it so; the bus ACL grants its names.
STANDIN_OVERRIDES: dict[str, Any] = {"clock": "/clock", "teleport_service": "/teleport", "map": "/map",
                                     "semantic": "/camera/semantic/image_raw", "max_angular_dps": 90.0,
                                     "angular_accel_dps2": 360.0, "base_radius_m": 0.1, "safety_distance_m": 0.05}


class UnknownProfileError(Ros2ProtocolError, ValueError):
    pass


def profile(name: str, overrides: dict[str, Any] | None = None) -> Ros2Profile:
    """The named profile with ``overrides`` applied (validated like the profile itself)."""
    try:
        base = PROFILES[name]
    except KeyError:
        raise UnknownProfileError(f"unknown robot profile {name!r}; known: {', '.join(sorted(PROFILES))}") from None
    if not overrides:
        return base
    return Ros2Profile.model_validate({**base.model_dump(), **overrides})
