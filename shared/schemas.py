"""Every message that crosses the bus, as pydantic v2 models.

One module, so a reader finds every payload of the system in one place (the key expressions that
carry them live in :mod:`shared.keys`). Conventions (frames, units, camera) are those of
:mod:`shared.geometry`. Images and clouds are numpy arrays (see :mod:`shared.arrays`); the binary
codec (:mod:`shared.codec`) moves them without copies.

Each model has a ``SCHEMA`` name and a ``VERSION``; the codec writes both into the envelope and
refuses a payload whose name or version does not match what the receiver expects.
"""

from __future__ import annotations

import math
import time
import unicodedata
from enum import StrEnum
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator, model_validator

from shared.arrays import Array
from shared.geometry import PinholeCamera

# --- limits -----------------------------------------------------------------------------------------
# Every number a request carries is finite (``allow_inf_nan=False`` on every model) and inside a stated
# range, checked when the message is decoded: a value outside it can only be a mistake or an attack,
# and once inside a robot's pose or a map it would poison every later request.

WORLD_LIMIT_M = 2.0e7  # |coordinate|: UTM northings reach 1e7 m; 1e300 is a mistake (nearness to the
# scene is checked where the scene is known: a start pose 1e6 m away gets a 422 with its distance)
ANGLE_LIMIT_RAD = 4.0 * math.pi  # |heading| or |turn|: two full turns either way
PITCH_LIMIT_RAD = math.pi / 2.0
TIME_LIMIT_S = 1.0e11  # timestamps: epoch seconds (~1.7e9) or simulated seconds (>= 0)
SEQ_LIMIT = 2**31 - 1  # ids, versions, sequence numbers, counts
LABEL_LIMIT = 2**31 - 1

Metres = Annotated[float, Field(ge=-WORLD_LIMIT_M, le=WORLD_LIMIT_M)]
Distance_m = Annotated[float, Field(ge=0.0, le=WORLD_LIMIT_M)]
Radians = Annotated[float, Field(ge=-ANGLE_LIMIT_RAD, le=ANGLE_LIMIT_RAD)]
Pitch_rad = Annotated[float, Field(ge=-PITCH_LIMIT_RAD, le=PITCH_LIMIT_RAD)]
Seconds = Annotated[float, Field(ge=0.0, le=TIME_LIMIT_S)]
Xyz_m = tuple[Metres, Metres, Metres]
LabelId = Annotated[int, Field(ge=-1, le=LABEL_LIMIT)]
Count = Annotated[int, Field(ge=0, le=SEQ_LIMIT)]
Cost_usd = Annotated[float, Field(ge=0.0, le=1e6)]
_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"  # a job id is one key segment (shared.keys.validate_segment)
Duration_s = Annotated[float, Field(ge=0.0, le=TIME_LIMIT_S)]


class BudgetExceeded(ValueError):
    """A well-formed request asks for more work or data than one request may (pixels, views, points,
    frames, bytes); the bus answers ``budget_exceeded`` and the gateway 413."""

    def __init__(self, what: str, asked: float, limit: float, unit: str = ""):
        u = f" {unit}" if unit else ""
        super().__init__(f"{what}: {asked:,.0f}{u} asked, at most {limit:,.0f}{u} per request")
        self.what, self.asked, self.limit = what, asked, limit


# Per-request budgets (data, not code): what one request may cost the service that answers it.
RENDER_MAX_PIXELS = 64 * 256 * 256  # views x width x height of one RenderRequest (~50 MB of reply)
PANORAMA_MAX_PIXELS = 12 * 512 * 512  # views x width x height of one panorama sent for prediction (~25 MB)
VIEW_MAX_PIXELS = 512 * 512  # one view of an observed panorama (the robot's own config sets the views)
MAP_CHUNK_MAX_POINTS = 2_000_000  # points of one MapChunk (~30 MB)
BUILD_MAX_RECORDINGS = 256
BUILD_MAX_FRAMES = 500_000  # frames of every recording of one BuildMapRequest together
IMPORT_MAX_BYTES = 256 << 20  # an imported cloud file
IMPORT_PART_BYTES = 4 << 20  # what a sender puts in one part of an upload (MapImportRequest.upload_id)
IMPORT_PART_MAX_BYTES = 32 << 20  # the most one part may carry
PATH_MAX_POINTS = 10_000  # trajectories and reference paths
FREE_FORM_MAX_ITEMS = 10_000  # values in a free-form dict (options, policy configs, event data)
FREE_FORM_MAX_ABS = 1e15  # |number| in a free-form dict; the typed config that reads it narrows it


def check_free_form(value: Any, what: str) -> Any:
    """``value`` (a free-form dict from HTTP or the bus) if every number in it is finite and in range
    and it is not absurdly large; else ValueError. What request models use on their ``dict[str, Any]``."""
    _free_form_check(value, what, [FREE_FORM_MAX_ITEMS])
    return value


def _free_form_check(value: Any, what: str, budget: list[int]) -> None:
    """Free-form (``dict[str, Any]``) fields escape the typed checks: refuse non-finite and huge
    numbers and absurd sizes in them too (the typed config that reads them narrows the ranges)."""
    budget[0] -= 1
    if budget[0] < 0:
        raise ValueError(f"{what}: more than {FREE_FORM_MAX_ITEMS} values")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if not math.isfinite(value):
            raise ValueError(f"{what} must be finite, got {value}")
        if abs(value) > FREE_FORM_MAX_ABS:
            raise ValueError(f"{what} must be within +-{FREE_FORM_MAX_ABS:g}, got {value:g}")
    elif isinstance(value, dict):
        for k, v in value.items():
            _free_form_check(v, f"{what}.{k}", budget)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _free_form_check(v, f"{what}[{i}]", budget)


class Message(BaseModel):
    """Base of every bus message."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid", frozen=False, allow_inf_nan=False)
    SCHEMA: ClassVar[str] = "message"
    VERSION: ClassVar[int] = 1
    FREE_FORM: ClassVar[tuple[str, ...]] = ()  # dict[str, Any] fields, checked by _free_form_check

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # Schema names default to the class name so that no two messages share one by accident.
        if "SCHEMA" not in cls.__dict__:
            cls.SCHEMA = cls.__name__

    @model_validator(mode="after")
    def _free_form_finite(self):
        for name in self.FREE_FORM:
            _free_form_check(getattr(self, name), name, [FREE_FORM_MAX_ITEMS])
        return self

    def check_budget(self) -> None:
        """Raise :class:`BudgetExceeded` when this request asks for more than one request may
        (the serving side calls it after decoding, before any work)."""


def _finite(values: tuple[float, ...] | float, what: str):
    vals = values if isinstance(values, tuple) else (values,)
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{what} must be finite, got {values}")
    return values


def _finite_array(arr: np.ndarray | None, what: str, non_negative: bool = False) -> None:
    """Refuse NaN/inf (and, for depths, negative values) in a float array payload: one bad value
    would silently poison a map, a splat or a distance downstream."""
    if arr is None or arr.dtype.kind != "f" or arr.size == 0:
        return
    bad = ~np.isfinite(arr)
    if non_negative:
        bad |= arr < 0
    if bad.any():
        rule = "finite and >= 0" if non_negative else "finite"
        raise ValueError(f"{what} must be {rule}; {int(bad.sum())} of {arr.size} values are not")


# --- geometry ------------------------------------------------------------------------------------


class Pose(Message):
    """Agent pose: floor point under the agent (metres, world z-up) and heading."""

    position_m: Xyz_m
    heading_rad: Radians = 0.0

    @property
    def xyz(self) -> np.ndarray:
        return np.asarray(self.position_m, dtype=np.float64)


class CameraIntrinsics(Message):
    width_px: int = Field(256, ge=8, le=4096)
    height_px: int = Field(256, ge=8, le=4096)
    hfov_deg: float = Field(90.0, ge=1.0, le=179.0)

    def pinhole(self) -> PinholeCamera:
        return PinholeCamera(self.width_px, self.height_px, self.hfov_deg)


class ViewPose(Message):
    """A camera to render from: agent floor position, heading and pitch."""

    position_m: Xyz_m
    heading_rad: Radians = 0.0
    pitch_rad: Pitch_rad = 0.0


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
    depth_noise_rel: float = Field(0.0, ge=0.0, le=0.5)

    @model_validator(mode="after")
    def _finite_values(self):
        _finite_array(self.depth_m, "depth_m", non_negative=True)
        return self


class MoveStatus(StrEnum):
    REACHED = "reached"
    BLOCKED = "blocked"


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

    recording: str
    start: bool
    rate_hz: float = Field(5.0, gt=0.0, le=60.0)
    # Frames are downscaled to this width before publishing (same field of view); None: full size.
    # Tours produce thousands of frames: 128 px keeps them to ~0.2 MB each.
    max_width_px: int | None = Field(128, ge=16, le=4096)


class RecordReply(Message):
    recording: str
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


# --- candidates, graphs, tours -------------------------------------------------------------------


class CandidateKind(StrEnum):
    WAYPOINT = "waypoint"
    BACKTRACK = "backtrack"
    STOP = "stop"


class Candidate(Message):
    """A possible action: a waypoint (dx, dy) in world axes, a backtrack, or stop."""

    index: int = Field(ge=0, le=10_000)
    kind: CandidateKind = CandidateKind.WAYPOINT
    dx_m: Metres = 0.0
    dy_m: Metres = 0.0
    angle_rad: Radians = 0.0  # relative to the agent heading, positive = left
    distance_m: Distance_m = 0.0
    score: float = Field(0.0, ge=-1e9, le=1e9)


class CandidateSet(Message):
    pose: Pose
    candidates: list[Candidate]


class NavNode(Message):
    node_id: str
    position_m: tuple[float, float, float]
    visited: bool
    region: int | None = None
    floor: int = 0


class NavEdge(Message):
    a: str
    b: str
    length_m: float


class NavGraph(Message):
    nodes: list[NavNode]
    edges: list[NavEdge]
    stairs: list[str] = Field(default_factory=list)


class Tour(Message):
    region: int
    start_pose: Pose
    hubs_m: Array("float64", 2)  # (K, 3) hub positions in visiting order
    path_m: Array("float64", 2)  # (P, 3) dense refined path
    coverage: float


class TourRecording(Message):
    """A finished recorded tour; its frames were published on ``IO_FRAMES`` under ``recording``."""

    exploration_id: str
    recording: str
    region: int = Field(ge=-1, le=100_000)
    start_pose: Pose
    frame_count: int = Field(ge=0, le=BUILD_MAX_FRAMES)


# --- maps ------------------------------------------------------------------------------------------


class MapInfo(Message):
    map_id: str
    version: int = Field(ge=1, le=SEQ_LIMIT)
    point_count: int = Field(ge=0, le=SEQ_LIMIT)
    bounds_min_m: Xyz_m
    bounds_max_m: Xyz_m
    source: str = ""
    has_labels: bool = False
    label_names: dict[LabelId, str] = Field(default_factory=dict)
    regions: int = Field(0, ge=0, le=100_000)
    scale_factors: list[Annotated[float, Field(gt=0.0, le=1e6)]] = Field(default_factory=list)
    timings_s: dict[str, Annotated[float, Field(ge=0.0, le=TIME_LIMIT_S)]] = Field(default_factory=dict)
    created_s: Seconds = Field(default_factory=time.time)


class MapListReply(Message):
    maps: list[MapInfo]


class MapRequest(Message):
    map_id: str
    version: int | None = Field(None, ge=1, le=2**31 - 1)  # None: latest


class MapChunkRequest(Message):
    map_id: str
    version: int | None = Field(None, ge=1, le=2**31 - 1)
    index: int = Field(0, ge=0, le=SEQ_LIMIT)
    max_points: int = Field(1_000_000, ge=1, le=10_000_000)

    def check_budget(self) -> None:
        if self.max_points > MAP_CHUNK_MAX_POINTS:
            raise BudgetExceeded("map chunk points", self.max_points, MAP_CHUNK_MAX_POINTS, "points")


class MapChunk(Message):
    """One slice of a map's points; ``count`` chunks together make the whole cloud."""

    map_id: str
    version: int
    index: int
    count: int
    xyz_m: Array("float32", 2, 3)
    rgb: Array("uint8", 2, 3)
    labels: Array("int32", 1) | None = None
    # shared.cloud.PointCloud.view_dirs: where each point was seen from (int8 unit vectors x 127).
    view_dirs: Array("int8", 2, 3) | None = None

    @model_validator(mode="after")
    def _finite_points(self):
        _finite_array(self.xyz_m, "xyz_m")
        n = len(self.xyz_m)
        for name, arr in (("rgb", self.rgb), ("labels", self.labels), ("view_dirs", self.view_dirs)):
            if arr is not None and len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} rows, xyz_m {n}")
        return self


# --- renderer --------------------------------------------------------------------------------------


# The renderer's splat modes (shared.pointrender.splat.SplatConfig.mode): the paper's fixed 3x3
# Gaussian, or the occlusion-correct visibility splatting with hole filling (issue 20).
SplatMode = Literal["paper", "visibility"]


class RenderRequest(Message):
    """Anticipated views of one step: every candidate's view in one request."""

    map_id: str
    version: int | None = Field(None, ge=1, le=2**31 - 1)
    views: list[ViewPose] = Field(min_length=1, max_length=64)
    camera: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    camera_height_m: float = Field(1.25, ge=0.0, le=3.0)
    with_labels: bool = True
    # Each view stands on the map's floor under it nearest to its given z, within this range (a
    # candidate on the stairs or another storey is seen from its own height); 0 keeps z as given.
    floor_search_m: float = Field(1.5, ge=0.0, le=5.0)
    splat_mode: SplatMode | None = None  # None: the renderer's configured mode

    def check_budget(self) -> None:
        px = len(self.views) * self.camera.width_px * self.camera.height_px
        if px > RENDER_MAX_PIXELS:
            raise BudgetExceeded("rendered pixels (views x width x height)", px, RENDER_MAX_PIXELS, "px")


class RenderResult(Message):
    map_id: str
    version: int
    rgb: Array("uint8", 4, 3)  # (B, H, W, 3)
    depth_m: Array("float32", 3)
    hole_mask: Array("bool", 3)
    labels: Array("int32", 3) | None = None
    render_s: float = 0.0
    splat_mode: SplatMode | None = None  # the mode that rendered these views (None: not said)


class SpatialMapRequest(Message):
    map_id: str
    version: int | None = Field(None, ge=1, le=2**31 - 1)
    pose: Pose
    trajectory_m: Array("float64", 2) | None = None  # (T, 3)
    candidates: list[Candidate] = Field(default_factory=list, max_length=1000)
    agent_up: bool = False
    size_px: int = Field(512, ge=64, le=2048)
    radius_m: float | None = Field(None, gt=0.0, le=WORLD_LIMIT_M)  # None: the whole floor

    @model_validator(mode="after")
    def _trajectory(self):
        t = self.trajectory_m
        if t is not None and t.size:
            if t.ndim != 2 or t.shape[1] != 3:
                raise ValueError(f"trajectory_m must be (T, 3), got {t.shape}")
            _finite_array(t, "trajectory_m")
            if np.abs(t).max() > WORLD_LIMIT_M:
                raise ValueError(f"trajectory_m: coordinates beyond +-{WORLD_LIMIT_M:.0f} m")
        return self

    def check_budget(self) -> None:
        n = 0 if self.trajectory_m is None else len(self.trajectory_m)
        if n > PATH_MAX_POINTS:
            raise BudgetExceeded("trajectory points", n, PATH_MAX_POINTS, "points")


class SpatialMapResult(Message):
    map_id: str
    version: int
    image: Array("uint8", 3, 3)
    metres_per_px: float
    render_s: float = 0.0


# --- planner / missions ----------------------------------------------------------------------------


class Decision(Message):
    """What the policy chose at one step."""

    candidate_index: int = Field(ge=0, le=10_000)
    kind: CandidateKind
    reasoning: str = ""
    backend: str = ""
    prompt_tokens: Count = 0
    completion_tokens: Count = 0
    cost_usd: Cost_usd = 0.0
    fallback: bool = False


class JobState(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"  # the policy stopped (whether at the goal is in the metrics)
    FAILED = "failed"
    CANCELLED = "cancelled"


def _meaningful_instruction(text: str) -> str:
    """An instruction is words: surrounding space is dropped, control characters (NUL, ...) are
    refused, and it must hold at least one letter (a NUL, "   " or "?!" tell a robot nothing)."""
    text = text.strip()
    bad = [c for c in text if unicodedata.category(c) == "Cc" and c not in "\t\n\r"]
    if bad:
        raise ValueError(f"instruction holds control characters ({', '.join(sorted({repr(c) for c in bad}))})")
    if not any(c.isalpha() for c in text):
        raise ValueError("instruction holds no words")
    return text


Instruction = Annotated[str, Field(min_length=1, max_length=4000), AfterValidator(_meaningful_instruction)]


class MissionOptions(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    policy: str = Field("heuristic", max_length=100)
    policy_config: dict[str, Any] = Field(default_factory=dict, description="the policy backend's config")
    max_steps: int = Field(40, ge=1, le=500)
    anticipation: bool = True
    anticipation_hfov_deg: float = Field(90.0, ge=30.0, le=150.0)
    # The renderer's splat mode for this mission's anticipated views (None: the renderer's configured one).
    anticipation_splat_mode: SplatMode | None = None
    # "map": rendered from the map (the method); "true-scene": ray-cast from the simulator's scene at the
    # same poses, an evaluation control bounding what anticipation can give (refused on a real robot).
    anticipation_views: Literal["map", "true-scene"] = "map"
    spatial_map: bool = True
    goal_m: Xyz_m | None = None
    reference_path_m: list[Xyz_m] | None = Field(None, max_length=PATH_MAX_POINTS)
    start_pose: Pose | None = None
    seed: int = Field(0, ge=0, le=2**32 - 1)
    record: bool | None = Field(None, description="write a Rerun recording (.rrd); None: the gateway's setting")

    @field_validator("policy_config")
    @classmethod
    def _policy_config(cls, v: dict[str, Any]) -> dict[str, Any]:
        _free_form_check(v, "policy_config", [FREE_FORM_MAX_ITEMS])
        return v


class MissionRequest(Message):
    mission_id: str
    instruction: Instruction
    map_id: str
    options: MissionOptions = Field(default_factory=MissionOptions)


class JobAccepted(Message):
    """A job's submission answered: accepted (its events follow on its events key) or refused, with why."""

    job_id: str
    accepted: bool
    reason: str = ""
    instance: str = ""  # the worker instance that took the job ("" : not said; the gateway then looks it up)


class CancelRequest(Message):
    mission_id: str


class JobEventKind(StrEnum):
    STARTED = "started"
    STEP = "step"
    PROGRESS = "progress"
    FINISHED = "finished"
    ERROR = "error"


# --- job events: one typed payload per kind of thing that happens to a mission or an exploration ---


class UsageData(BaseModel):
    """The policy's running cost: LLM calls, tokens and dollars so far (all counters, so >= 0)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    calls: Count = 0
    prompt_tokens: Count = 0
    completion_tokens: Count = 0
    cost_usd: Cost_usd = 0.0
    reasks: Count = 0
    fallbacks: Count = 0
    cache_hits: Count = 0

    def add(self, other: UsageData) -> None:
        """Accumulate ``other`` into this one (a policy sums each step's usage into its mission's)."""
        for name in type(self).model_fields:
            setattr(self, name, getattr(self, name) + getattr(other, name))


class EpisodeMetricsData(BaseModel):
    """The VLN-CE metrics of one mission (:class:`shared.vln_metrics.EpisodeMetrics` on the wire)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    ne_m: Distance_m | None
    success: bool
    oracle_success: bool
    oracle_ne_m: Distance_m | None
    tl_m: Distance_m
    spl: float = Field(ge=0.0, le=1.0)
    ndtw: float | None = Field(ge=0.0, le=1.0)
    sdtw: float | None = Field(ge=0.0, le=1.0)
    shortest_m: Distance_m | None
    stop_called: bool
    steps: Count
    goal_reachable: bool


class EventPayload(BaseModel):
    """Base of every job event payload. ``type`` tells the payloads apart on the wire; ``KINDS`` are the
    event kinds a payload may travel with (checked by :class:`JobEvent`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    KINDS: ClassVar[tuple[str, ...]] = ()


def _finite_xyz(points: list[tuple[float, float, float]], what: str):
    for p in points:
        _finite(p, what)
    return points


class MissionStarted(EventPayload):
    KINDS: ClassVar[tuple[str, ...]] = ("started",)
    type: Literal["mission_started"] = "mission_started"
    pose: Pose
    instruction: str
    map_id: str
    options: MissionOptions


class MissionStep(EventPayload):
    """One navigation step: where the agent was, what it could do, what it chose and what that cost."""

    KINDS: ClassVar[tuple[str, ...]] = ("step",)
    type: Literal["mission_step"] = "mission_step"
    pose: Pose
    candidates: list[Candidate]
    decision: Decision
    timings_s: dict[str, Duration_s] = Field(default_factory=dict)
    usage: UsageData = Field(default_factory=UsageData)


class MissionEnd(StrEnum):
    """How a mission ended - apart from whether it reached its goal (``success``, known only when the
    mission has a goal): ``policy_stopped`` says only that the policy stopped, never that it was right."""

    POLICY_STOPPED = "policy_stopped"  # the policy chose stop
    NO_WAY_TO_MOVE = "no_way_to_move"  # stop was the only action left (boxed in)
    MAX_STEPS = "max_steps"  # the step budget ran out without a stop
    CANCELLED = "cancelled"
    FAILED = "failed"


_FINISHED_ENDS = {MissionEnd.POLICY_STOPPED: True, MissionEnd.NO_WAY_TO_MOVE: True, MissionEnd.MAX_STEPS: False}


class MissionFinished(EventPayload):
    """The mission's end: the path walked, its metrics when a goal was known, the policy's total cost.
    ``reason`` qualifies a stop (e.g. boxed in); ``error`` is the cause of a failure.

    ``outcome`` is the planner's word on how the loop ended (only the planner knows that stop was the
    only action left); a sender that does not say gets the one ``stop_called`` implies. ``success``
    exists only with a goal, and is the metrics' success."""

    KINDS: ClassVar[tuple[str, ...]] = ("finished",)
    type: Literal["mission_finished"] = "mission_finished"
    stop_called: bool
    steps: Count
    outcome: MissionEnd | None = None
    success: bool | None = None
    trajectory_m: list[Xyz_m] = Field(default_factory=list, max_length=PATH_MAX_POINTS)
    metrics: EpisodeMetricsData | None = None
    usage: UsageData = Field(default_factory=UsageData)
    step_latency_s: list[Duration_s] = Field(default_factory=list, max_length=PATH_MAX_POINTS)
    reason: str = ""
    error: str = ""

    @field_validator("trajectory_m")
    @classmethod
    def _trajectory_finite(cls, v):
        return _finite_xyz(v, "trajectory_m")

    @model_validator(mode="after")
    def _outcome_and_success(self):
        if self.outcome is None:
            self.outcome = MissionEnd.POLICY_STOPPED if self.stop_called else MissionEnd.MAX_STEPS
        if self.outcome not in _FINISHED_ENDS:
            raise ValueError(f"outcome {self.outcome.value!r}: a cancelled or failed mission ends with its own event")
        if _FINISHED_ENDS[self.outcome] != self.stop_called:
            raise ValueError(f"outcome {self.outcome.value!r} disagrees with stop_called={self.stop_called}")
        if self.metrics is None:
            if self.success is not None:
                raise ValueError("success exists only when a goal is known (no metrics)")
        elif self.success is None:
            self.success = self.metrics.success
        elif self.success != self.metrics.success:
            raise ValueError(f"success={self.success} disagrees with the metrics' success={self.metrics.success}")
        return self


class ExplorationStarted(EventPayload):
    KINDS: ClassVar[tuple[str, ...]] = ("started",)
    type: Literal["exploration_started"] = "exploration_started"
    map_id: str


class ExplorationOutcome(BaseModel):
    """How an exploration ended: on an exhausted frontier (``finished``), or on a safety budget."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    finished: bool
    stop_reason: Literal["exhausted", "steps", "moves", "time"]
    steps: Count
    step_budget: Count
    moves: Count
    discovered_m2: float = Field(ge=0.0, le=WORLD_LIMIT_M**2)
    coverage_estimate: float = Field(ge=0.0, le=1.0)
    open_stairs: Count = 0  # stair nodes past the last explored floor: a flight leads on
    mapped_free_m2: float = Field(0.0, ge=0.0, le=WORLD_LIMIT_M**2)  # free floor in the explorer's own map
    map_frontiers: Count = 0  # targets the map's frontiers added where the predictor proposed none
    narrow_frontiers: Count = 0  # ... of them behind passages only a narrower body than the planned one passes
    open_frontiers: Count = 0  # frontiers no visited node came near and none was tried when it ended


class StageProgress(EventPayload):
    """How far a long job has come: its stage, a fraction in [0, 1], and the region it is at."""

    KINDS: ClassVar[tuple[str, ...]] = ("progress",)
    stage: str
    progress: float = Field(ge=0.0, le=1.0)
    message: str = ""
    region: int | None = Field(None, ge=-1, le=100_000)
    regions: Count | None = None


class ExplorationProgress(StageProgress):
    """A stage of an exploration (exploring, touring, reconstructing)."""

    type: Literal["exploration_progress"] = "exploration_progress"
    frames: Count | None = None
    nodes: Count | None = None
    timings_s: dict[str, Duration_s] = Field(default_factory=dict)
    outcome: ExplorationOutcome | None = None


class ExplorationFinished(EventPayload):
    """The stored map an exploration produced, and what the exploration took."""

    KINDS: ClassVar[tuple[str, ...]] = ("finished",)
    type: Literal["exploration_finished"] = "exploration_finished"
    stage: str = "done"
    progress: float = Field(1.0, ge=0.0, le=1.0)
    map_id: str
    version: int = Field(ge=1, le=SEQ_LIMIT)
    points: Count
    regions: Count
    skipped_regions: list[Annotated[int, Field(ge=-1, le=100_000)]] = Field(default_factory=list)
    nodes: Count = 0
    wall_s: Duration_s = 0.0
    timings_s: dict[str, Duration_s] = Field(default_factory=dict)
    outcome: ExplorationOutcome | None = None


class MapBuildProgress(StageProgress):
    """A map build's stage (collecting frames, reconstructing region k of n, storing)."""

    type: Literal["map_build_progress"] = "map_build_progress"


class MapBuildFinished(EventPayload):
    """The map version a build stored."""

    KINDS: ClassVar[tuple[str, ...]] = ("finished",)
    type: Literal["map_build_finished"] = "map_build_finished"
    info: MapInfo


class JobCancelled(EventPayload):
    """A job's end on request; ``stage`` is the stage of a staged job (an exploration, a map build) it
    was stopped in (None: a job without stages, or stopped before its first)."""

    KINDS: ClassVar[tuple[str, ...]] = ("finished",)
    type: Literal["job_cancelled"] = "job_cancelled"
    message: str = "cancelled on request"
    stage: str | None = Field(None, max_length=64)


class JobFailed(EventPayload):
    """Any job's failure, with its cause."""

    KINDS: ClassVar[tuple[str, ...]] = ("error",)
    type: Literal["job_failed"] = "job_failed"
    error: str


EventData = Annotated[
    MissionStarted | MissionStep | MissionFinished | ExplorationStarted | ExplorationProgress
    | ExplorationFinished | MapBuildProgress | MapBuildFinished | JobCancelled | JobFailed,
    Field(discriminator="type"),
]


class JobEvent(Message):
    """One thing that happened to a job (a mission, an exploration, a map build); ``seq`` orders the
    events of one job, gap-free from 0, and exactly one event has a terminal state.

    ``data`` is the kind's typed payload (None only for events that carry nothing); pictures travel
    JPEG-encoded in ``images`` (name -> bytes) so the gateway can store them once and serve them by URL
    instead of inlining them in every event.
    """

    job_id: str
    seq: int = Field(ge=0, le=SEQ_LIMIT)
    kind: JobEventKind
    state: JobState
    step: int = Field(0, ge=0, le=100_000)
    timestamp_s: Seconds = Field(default_factory=time.time)
    data: EventData | None = None
    images: dict[str, bytes] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _payload_fits_kind(self):
        if self.data is not None and self.kind.value not in self.data.KINDS:
            raise ValueError(f"a {self.data.type} payload cannot travel in a {self.kind.value!r} event")
        return self

    def data_json(self) -> dict[str, Any]:
        """The payload as JSON-ready values (what the gateway stores and streams)."""
        return {} if self.data is None else self.data.model_dump(mode="json")


class ExplorationRequest(Message):
    """Pre-explore the robot's current scene, record tours and reconstruct a map named ``map_id``."""

    exploration_id: str
    map_id: str
    # A hard cap on panoramas; None leaves the mapper's safety budget, which scales with the area
    # discovered (the exploration otherwise ends when no frontier is left).
    max_steps: int | None = Field(None, ge=1, le=100_000)
    reconstruction: str = Field("rgbd", description="regional reconstruction backend (rgbd, mono, ...)")
    options: dict[str, Any] = Field(default_factory=dict)
    record: bool | None = Field(None, description="write a Rerun recording (.rrd); None: the gateway's setting")

    FREE_FORM: ClassVar[tuple[str, ...]] = ("options",)


class ExplorationCancelRequest(Message):
    """Stop a running exploration (``EXPLORATION_CANCEL``): whose robot is the key's, which exploration
    this says. Its ``cancelled`` event (with the stage it stopped in) follows on its events key."""

    exploration_id: str = Field(pattern=_ID_PATTERN)


class BuildCancelRequest(Message):
    """Stop a map build (``MAP_BUILD_CANCEL``): the map is the key's, the build this says. A cancelled
    build stores nothing: the map store keeps only the versions it had."""

    build_id: str = Field(pattern=_ID_PATTERN)


class BuildMapRequest(Message):
    """Mapper -> reconstructor: the recorded tours of an exploration are complete; build the map.

    A build is a job: the reply is a :class:`JobAccepted`, its events follow on ``MAP_BUILD_EVENTS``
    under ``build_id``."""

    build_id: str
    exploration_id: str
    map_id: str
    recordings: list[TourRecording] = Field(max_length=BUILD_MAX_RECORDINGS)
    reconstruction: str = "rgbd"
    label_names: dict[LabelId, str] = Field(default_factory=dict, description="semantic ids of the frames")
    source: str = ""
    options: dict[str, Any] = Field(default_factory=dict)

    FREE_FORM: ClassVar[tuple[str, ...]] = ("options",)

    def check_budget(self) -> None:
        frames = sum(r.frame_count for r in self.recordings)
        if frames > BUILD_MAX_FRAMES:
            raise BudgetExceeded("frames of the recordings", frames, BUILD_MAX_FRAMES, "frames")


class MapImportRequest(Message):
    """Store a user's own cloud (PLY or PCD bytes) as a map: whole in one request, or in parts.

    In parts (``upload_id`` set), so that no side ever holds the file whole: each part carries the
    bytes at ``offset`` (the parts in order, no gaps); the receiver appends them to a file on disk and
    answers :class:`MapImportProgress`, and the ``last`` part's answer is the stored map's
    :class:`MapInfo`. An ``abort`` part (no data) drops what was received. Any failure drops the
    whole upload: a failed upload leaves neither a map nor a partial file."""

    map_id: str
    filename: str = Field(pattern=r"^[^/\\\x00-\x1f]{1,200}\.(ply|pcd)$")
    data: bytes = b""
    upload_id: str | None = Field(None, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    offset: int = Field(0, ge=0, le=IMPORT_MAX_BYTES, description="bytes of the upload before this part")
    last: bool = True
    abort: bool = False

    @model_validator(mode="after")
    def _parts_agree(self):
        if self.upload_id is None and (self.offset or self.abort or not self.last):
            raise ValueError("offset, abort and last=False belong to an upload in parts (set upload_id)")
        if self.abort and self.data:
            raise ValueError("an abort part carries no data")
        if not self.abort and not self.data:
            raise ValueError("data: an import needs at least one byte")
        return self

    def check_budget(self) -> None:
        if self.offset + len(self.data) > IMPORT_MAX_BYTES:
            raise BudgetExceeded("imported cloud bytes", self.offset + len(self.data), IMPORT_MAX_BYTES, "bytes")
        if self.upload_id is not None and len(self.data) > IMPORT_PART_MAX_BYTES:
            raise BudgetExceeded("bytes of one upload part", len(self.data), IMPORT_PART_MAX_BYTES, "bytes")


class MapImportProgress(Message):
    """The answer to a part of an upload that is not the last (or to an abort)."""

    upload_id: str
    received_bytes: int = Field(ge=0, le=IMPORT_MAX_BYTES)


# --- service plumbing ------------------------------------------------------------------------------


class Ping(Message):
    pass


class ServiceInfo(Message):
    service: str
    version: str
    instance: str
    backends: dict[str, str] = Field(default_factory=dict)
    started_s: float = 0.0
    healthy: bool = True  # False: alive, but its state is broken (``problem`` says how)
    problem: str = ""


class EndpointStats(Message):
    requests: int = 0
    errors: int = 0
    latency_p50_ms: float = 0.0
    latency_p99_ms: float = 0.0
    queue_depth: int = 0


class ServiceMetrics(Message):
    service: str
    instance: str
    uptime_s: float
    endpoints: dict[str, EndpointStats] = Field(default_factory=dict)


class ErrorCode(StrEnum):
    BAD_REQUEST = "bad_request"  # undecodable, wrong schema, invalid fields
    NOT_FOUND = "not_found"
    UNAVAILABLE = "unavailable"
    INTERNAL = "internal"
    TIMEOUT = "timeout"
    BUDGET_EXCEEDED = "budget_exceeded"  # a well-formed request over a per-request budget


class ErrorReply(Message):
    """What a queryable answers instead of its result when something went wrong."""

    code: ErrorCode
    message: str
    service: str = ""

