"""Robot-io's messages: panoramas, frames, motion, recordings and scene summaries."""

from __future__ import annotations

import math
import time
from enum import StrEnum

from pydantic import Field, model_validator

from shared.arrays import Array

from .base import (
    SegmentId,
    DepthNoiseRel,
    _finite_array,
    BudgetExceeded,
    Message,
    PANORAMA_MAX_PIXELS,
    Pitch_rad,
    Radians,
    RENDER_MAX_PIXELS,
    Seconds,
    SEQ_LIMIT,
    VIEW_MAX_PIXELS,
    Xyz_m,
)
from .geometry import CameraIntrinsics, Pose, ViewPose


# --- robot-io ------------------------------------------------------------------------------------


class Panorama(Message):
    """12 (configurable) RGB-D views around the agent; view i looks at headings_rad[i]."""

    pose: Pose
    camera: CameraIntrinsics
    headings_rad: Array("float64", 1)
    rgb: Array("uint8", 4, 3)  # (V, H, W, 3)
    depth_m: Array("float32", 3)  # (V, H, W), z-depth, 0 = no measurement
    semantic: Array("int32", 3) | None = None  # (V, H, W) class ids, -1 = unknown
    timestamp_s: Seconds = Field(default_factory=time.time)
    # The depth sensor's noise as its robot declares it, as on a Frame: sigma = depth_noise_rel *
    # depth^2. 0: exact, or not known. The waypoint predictor smooths depth only within that noise.
    depth_noise_rel: DepthNoiseRel = 0.0

    @model_validator(mode="after")
    def _shapes(self):
        v = self.headings_rad.shape[0]
        hw = (self.camera.height_px, self.camera.width_px)
        if self.rgb.shape != (v, *hw, 3) or self.depth_m.shape != (v, *hw):
            raise ValueError(
                f"panorama shapes disagree: {v} headings, rgb {self.rgb.shape}, "
                f"depth {self.depth_m.shape}, camera {hw}"
            )
        if self.semantic is not None and self.semantic.shape != (v, *hw):
            raise ValueError(f"semantic shape {self.semantic.shape} != {(v, *hw)}")
        _finite_array(self.headings_rad, "headings_rad")
        _finite_array(self.depth_m, "depth_m", non_negative=True)
        return self

    def check_budget(self) -> None:
        px = self.rgb.shape[0] * self.camera.width_px * self.camera.height_px
        if px > PANORAMA_MAX_PIXELS:
            raise BudgetExceeded("panorama pixels (views x width x height)", px, PANORAMA_MAX_PIXELS, "px")


class Frame(Message):
    """One recorded video frame of a tour (RGB, optional depth, pose and IMU heading)."""

    index: int = Field(ge=0, le=SEQ_LIMIT)
    timestamp_s: Seconds
    pose: Pose
    pitch_rad: Pitch_rad = 0.0
    imu_heading_rad: Radians
    camera: CameraIntrinsics
    rgb: Array("uint8", 3, 3)
    depth_m: Array("float32", 2) | None = None
    semantic: Array("int32", 2) | None = None
    # The depth sensor's noise as its robot declares it: sigma = depth_noise_rel * depth^2 (a stereo
    # or structured-light camera's error grows with the square of the range). 0: exact, or not known.
    # The reconstructor fuses a frame's depth only as far as that noise stays near a voxel.
    depth_noise_rel: DepthNoiseRel = 0.0

    @model_validator(mode="after")
    def _finite_values(self):
        _finite_array(self.depth_m, "depth_m", non_negative=True)
        return self


class MoveStatus(StrEnum):
    REACHED = "reached"
    BLOCKED = "blocked"
    # The robot's own planner found no way there (Nav2: goal occupied, outside the map, no valid path):
    # the robot did not set off.
    UNREACHABLE = "unreachable"


class SceneViewsRequest(Message):
    """Views at given poses ray-cast from the simulator's true scene (RGB, depth, semantic), in the
    robot's reported frame like a render request: what a perfect map would show there."""

    views: list[ViewPose] = Field(min_length=1, max_length=64)
    camera: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    with_semantic: bool = True

    def check_budget(self) -> None:
        px = len(self.views) * self.camera.width_px * self.camera.height_px
        if px > RENDER_MAX_PIXELS:
            raise BudgetExceeded("rendered pixels (views x width x height)", px, RENDER_MAX_PIXELS, "px")


class ObserveRequest(Message):
    camera: CameraIntrinsics | None = None  # None: the robot's configured camera
    with_semantic: bool = True

    def check_budget(self) -> None:
        px = 0 if self.camera is None else self.camera.width_px * self.camera.height_px
        if px > VIEW_MAX_PIXELS:
            raise BudgetExceeded("pixels per observed view", px, VIEW_MAX_PIXELS, "px")


class MoveRequest(Message):
    """Walk to a waypoint given as an offset in world axes (paper: p + (dx, dy))."""

    dx_m: float = Field(ge=-20.0, le=20.0)
    dy_m: float = Field(ge=-20.0, le=20.0)

    @model_validator(mode="after")
    def _within_reach(self):
        if math.hypot(self.dx_m, self.dy_m) > 20.0:
            raise ValueError("a single move_to is limited to 20 m")
        return self


class MoveResult(Message):
    status: MoveStatus
    pose: Pose
    travelled_m: float
    steps: int


class TurnRequest(Message):
    angle_rad: Radians  # positive turns left (counter-clockwise)


class ResetRequest(Message):
    pose: Pose | None = None  # None: the scene's start pose


class PoseReply(Message):
    pose: Pose


class RecordRequest(Message):
    """Start or stop recording a tour: while on, every motion publishes Frames on IO_FRAMES."""

    recording: SegmentId
    start: bool
    rate_hz: float = Field(5.0, gt=0.0, le=60.0)
    # Frames are downscaled to this width before publishing (same field of view); None: full size.
    # Tours produce thousands of frames: 128 px keeps them to ~0.2 MB each.
    max_width_px: int | None = Field(128, ge=16, le=4096)


class RecordReply(Message):
    recording: SegmentId
    recording_on: bool
    frame_count: int


class RoomInfo(Message):
    """A labelled room: the box it fills, from its floor up to its ceiling (world metres)."""

    name: str  # unique: "bedroom", "bedroom 2", ...
    room_type: str
    floor: int = Field(0, ge=0)
    bounds_min_m: tuple[float, float, float]
    bounds_max_m: tuple[float, float, float]
    area_m2: float = Field(0.0, ge=0.0, allow_inf_nan=False)


class ObjectInfo(Message):
    """A labelled object (furniture) with its footprint box."""

    object_id: int = Field(ge=0)
    label: str
    colour: str
    description: str  # "green plant": how instructions name it
    room: str
    position_m: tuple[float, float, float]  # centre of the footprint, on the floor
    size_m: tuple[float, float, float]  # extent along world x, y, z
    yaw_rad: float = Field(allow_inf_nan=False)


class SceneSummary(Message):
    """What robot-io tells others about its scene: the one scene description of the system.

    The simulator knows all of it; a real robot may know only its bounds (and its map's labels), so
    everything past the bounds has an empty default."""

    scene: str
    source: str = ""
    bounds_min_m: tuple[float, float, float]
    bounds_max_m: tuple[float, float, float]
    floors: int = Field(1, ge=1)
    triangle_count: int = Field(0, ge=0)
    reachable_area_m2: float = Field(0.0, ge=0.0, allow_inf_nan=False)  # of the agent's main walkable region
    nav_cell_m: float | None = Field(None, gt=0.0)
    label_names: dict[int, str] = Field(default_factory=dict)  # semantic id -> class name; -1 is not listed
    rooms: list[RoomInfo] = Field(default_factory=list)
    objects: list[ObjectInfo] = Field(default_factory=list)
    start_pose: Pose | None = None

    def room(self, name: str) -> RoomInfo:
        for r in self.rooms:
            if r.name == name:
                return r
        raise KeyError(name)


class LoadSceneRequest(Message):
    """Switch the simulator to another scene (generated:<seed>[:floors=2], or a mesh path)."""

    scene: str = Field(min_length=1, max_length=1000)


class GeodesicRequest(Message):
    start_m: Xyz_m
    goal_m: Xyz_m


class GeodesicReply(Message):
    distance_m: float | None  # None: no path (unreachable goal)
    path_m: Array("float64", 2) | None = None
    # How far each end lies from walkable ground (None: the backend cannot tell): what a caller
    # checks before trusting a start pose or a goal (a point 1e6 m away snaps to some corner).
    start_off_m: float | None = None
    goal_off_m: float | None = None
