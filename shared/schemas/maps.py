"""Maps: listing, chunks, builds and imports."""

from __future__ import annotations

import time
from typing import Annotated, Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.arrays import Array

from .base import (
    SegmentId,
    _finite_array,
    BudgetExceeded,
    BUILD_MAX_FRAMES,
    BUILD_MAX_RECORDINGS,
    Cost_usd,
    Count,
    IMPORT_MAX_BYTES,
    IMPORT_PART_MAX_BYTES,
    LabelId,
    MAP_CHUNK_MAX_POINTS,
    Message,
    Seconds,
    SEQ_LIMIT,
    TIME_LIMIT_S,
    Xyz_m,
)
from .navigation import NavGraph, TourRecording


# --- maps ------------------------------------------------------------------------------------------


class MapLabelling(BaseModel):
    """Who named the rooms of a map version's scene graph and what that cost (issue 32): the store's
    labeller backend (``sim`` | ``none`` | ``mllm``), the chat model it asked, the calls and tokens
    (the counters of :class:`~shared.schemas.UsageData`), and ``error`` when the labeller failed and the
    version kept the geometric graph (rooms unnamed)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    labeller: str = Field(pattern=r"^[a-z][a-z0-9_-]{0,31}$")
    model: str = Field("", max_length=200)
    regions: Count = 0  # regions the labeller was given frames of
    rooms_named: Count = 0
    calls: Count = 0
    prompt_tokens: Count = 0
    completion_tokens: Count = 0
    cost_usd: Cost_usd = 0.0
    reasks: Count = 0
    cache_hits: Count = 0
    error: str = Field("", max_length=1000)


class RegionDriftCorrection(Message):
    """How one region of a built map was corrected for odometry drift (issue 33)."""

    region: int = Field(ge=0, le=100_000)
    anchor: bool = False  # the region the others were registered to; it never moves
    fell_back: bool = False  # no trustworthy registration: the region kept its recorded poses
    reason: str = Field("", max_length=64)  # why it fell back ("no overlap", "no gain", ...)
    correction_m: float = Field(0.0, ge=0.0, le=1000.0)  # the region's planar correction applied
    correction_deg: float = Field(0.0, ge=0.0, le=180.0)
    fitness: float | None = Field(None, ge=0.0, le=1.0)  # matched fraction of its overlap
    rmse_m: float | None = Field(None, ge=0.0, le=1000.0)  # point-to-plane residual after
    frames_registered: int = Field(0, ge=0, le=SEQ_LIMIT)  # within the region (frame to model)
    frames_fallback: int = Field(0, ge=0, le=SEQ_LIMIT)


class PoseGraphSummary(Message):
    """The mapper's pose graph over its panoramas (issue 33), as its last solve before the build left
    it: the scan-to-scan edges it used and rejected (loop closures: pairs far apart along the path),
    and how far the panoramas' poses lie from odometry's."""

    panoramas: int = Field(0, ge=0, le=SEQ_LIMIT)
    scan_edges: int = Field(0, ge=0, le=SEQ_LIMIT)  # accepted
    # Of the accepted edges, those pinned one way only (through a door, along a corridor), which only the
    # final solve before the build takes (the mapper's PoseGraphConfig.final_weak_edges).
    weak_edges: int = Field(0, ge=0, le=SEQ_LIMIT)
    edges_rejected: int = Field(0, ge=0, le=SEQ_LIMIT)
    loop_closures_accepted: int = Field(0, ge=0, le=SEQ_LIMIT)
    loop_closures_rejected: int = Field(0, ge=0, le=SEQ_LIMIT)
    applied: bool = False  # False: every panorama within the gate of its sequential placement
    panoramas_corrected: int = Field(0, ge=0, le=SEQ_LIMIT)  # placed off their odometry pose
    median_correction_m: float = Field(0.0, ge=0.0, le=1000.0)
    max_correction_m: float = Field(0.0, ge=0.0, le=1000.0)
    max_correction_deg: float = Field(0.0, ge=0.0, le=180.0)
    # The exploration's graph nodes moved with the panoramas when the exploration ended (so the
    # regions, hubs, tours and scene graph agree with the map): how many, and how far.
    nodes_moved: int = Field(0, ge=0, le=SEQ_LIMIT)
    median_node_shift_m: float = Field(0.0, ge=0.0, le=1000.0)
    max_node_shift_m: float = Field(0.0, ge=0.0, le=1000.0)


class DriftCorrection(Message):
    """Whether and how a built map was corrected for drift; ``applied`` False says plainly that the
    map is placed by the recorded poses alone."""

    applied: bool = False
    method: str = Field("", max_length=32)  # region stage: "sequential" or "graph"; "" when off
    frames: bool = False  # frames registered within regions
    regions: bool = False  # regions registered to each other
    regions_corrected: int = Field(0, ge=0, le=100_000)
    regions_fallback: int = Field(0, ge=0, le=100_000)
    max_correction_m: float = Field(0.0, ge=0.0, le=1000.0)
    max_correction_deg: float = Field(0.0, ge=0.0, le=180.0)
    loop_closures_accepted: int = Field(0, ge=0, le=100_000)
    loop_closures_rejected: int = Field(0, ge=0, le=100_000)
    # The mapper's own map <- odom correction (its online localiser), applied to each tour's frames
    # before any registration above: tours that carried a non-zero one, and how large it was per tour
    # (the largest in effect during the tour). A robot without a localiser is corrected here first.
    odom_regions_corrected: int = Field(0, ge=0, le=100_000)
    odom_median_correction_m: float = Field(0.0, ge=0.0, le=1000.0)
    odom_max_correction_m: float = Field(0.0, ge=0.0, le=1000.0)
    odom_max_correction_deg: float = Field(0.0, ge=0.0, le=180.0)
    pose_graph: PoseGraphSummary | None = None  # the mapper's panoramas (None: no graph was solved)
    per_region: list[RegionDriftCorrection] = Field(default_factory=list, max_length=100_000)


class MapInfo(Message):
    map_id: SegmentId
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
    labelling: MapLabelling | None = None  # None: stored before labellers were (or a streamed import)


    # Built maps only (None: imported, or stored before issue 33).
    drift_correction: DriftCorrection | None = None


class MapListReply(Message):
    maps: list[MapInfo]


class MapRequest(Message):
    map_id: SegmentId
    version: int | None = Field(None, ge=1, le=2**31 - 1)  # None: latest


class MapChunkRequest(Message):
    map_id: SegmentId
    version: int | None = Field(None, ge=1, le=2**31 - 1)
    index: int = Field(0, ge=0, le=SEQ_LIMIT)
    max_points: int = Field(1_000_000, ge=1, le=10_000_000)

    def check_budget(self) -> None:
        if self.max_points > MAP_CHUNK_MAX_POINTS:
            raise BudgetExceeded("map chunk points", self.max_points, MAP_CHUNK_MAX_POINTS, "points")


class MapChunk(Message):
    """One slice of a map's points; ``count`` chunks together make the whole cloud."""

    map_id: SegmentId
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


class BuildCancelRequest(Message):
    """Stop a map build (``MAP_BUILD_CANCEL``): the map is the key's, the build this says. A cancelled
    build stores nothing: the map store keeps only the versions it had."""

    build_id: SegmentId


class BuildMapRequest(Message):
    """Mapper -> reconstructor: the recorded tours of an exploration are complete; build the map.

    A build is a job: the reply is a :class:`JobAccepted`, its events follow on ``MAP_BUILD_EVENTS``
    under ``build_id``."""

    build_id: SegmentId
    exploration_id: SegmentId
    map_id: SegmentId
    recordings: list[TourRecording] = Field(max_length=BUILD_MAX_RECORDINGS)
    reconstruction: str = "rgbd"
    label_names: dict[LabelId, str] = Field(default_factory=dict, description="semantic ids of the frames")
    source: str = ""
    options: dict[str, Any] = Field(default_factory=dict)
    # The exploration's navigation graph: stored with the map, part of its scene graph (issue 32).
    navigation: NavGraph | None = None
    # The mapper's pose graph that placed the recordings' corrections (issue 33); kept in the map's record.
    pose_graph: PoseGraphSummary | None = None

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

    map_id: SegmentId
    filename: str = Field(pattern=r"^[^/\\\x00-\x1f]{1,200}\.(ply|pcd)$")
    data: bytes = b""
    upload_id: SegmentId | None = None
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

    upload_id: SegmentId
    received_bytes: int = Field(ge=0, le=IMPORT_MAX_BYTES)
