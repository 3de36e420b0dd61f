"""Job events: one typed payload per kind of thing that happens to a mission, an exploration or a build."""

from __future__ import annotations

import time
from enum import StrEnum
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from .base import (
    SegmentId,
    _finite,
    Cost_usd,
    Count,
    DepthNoiseRel,
    Distance_m,
    Duration_s,
    Message,
    PATH_MAX_POINTS,
    Seconds,
    SEQ_LIMIT,
    WORLD_LIMIT_M,
    Xyz_m,
)
from .geometry import Pose
from .maps import MapInfo
from .missions import Decision, JobEventKind, JobState, MissionOptions
from .navigation import Candidate


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
    map_id: SegmentId
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
    map_id: SegmentId


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
    # The largest depth noise the robot's panoramas declared (sigma = rel * depth^2; 0: exact or not known):
    # the tours then look from nearer (the mapper's TourConfig.max_depth_sigma_m).
    depth_noise_rel: DepthNoiseRel = 0.0


class StageProgress(EventPayload):
    """How far a long job has come: its stage, a fraction in [0, 1], and the region it is at."""

    KINDS: ClassVar[tuple[str, ...]] = ("progress",)
    stage: str
    progress: float = Field(ge=0.0, le=1.0)
    message: str = ""
    region: int | None = Field(None, ge=-1, le=100_000)
    regions: Count | None = None


class ExplorationProgress(StageProgress):
    """A stage of an exploration (exploring, touring, reconstructing). While exploring, every step
    says where the frontier DFS stands: panoramas taken, nodes visited and seen, open frontiers,
    floors, a coverage estimate (refreshed every few seconds, not every step), elapsed wall time and a
    rate-based estimate of the exploration's time left (None: no rate yet)."""

    type: Literal["exploration_progress"] = "exploration_progress"
    frames: Count | None = None
    nodes: Count | None = None
    timings_s: dict[str, Duration_s] = Field(default_factory=dict)
    outcome: ExplorationOutcome | None = None
    step: Count | None = None
    visited: Count | None = None
    seen: Count | None = None
    open_frontiers: Count | None = None
    floors: Count | None = None
    coverage_estimate: float | None = Field(None, ge=0.0, le=1.0)
    elapsed_s: Duration_s | None = None
    time_left_s: Duration_s | None = None


class ExplorationFinished(EventPayload):
    """The stored map an exploration produced, and what the exploration took."""

    KINDS: ClassVar[tuple[str, ...]] = ("finished",)
    type: Literal["exploration_finished"] = "exploration_finished"
    stage: str = "done"
    progress: float = Field(1.0, ge=0.0, le=1.0)
    map_id: SegmentId
    version: int = Field(ge=1, le=SEQ_LIMIT)
    points: Count
    regions: Count
    skipped_regions: list[Annotated[int, Field(ge=-1, le=100_000)]] = Field(default_factory=list)
    nodes: Count = 0
    wall_s: Duration_s = 0.0
    timings_s: dict[str, Duration_s] = Field(default_factory=dict)
    outcome: ExplorationOutcome | None = None
    # What naming the map's rooms cost (the store's MLLM labeller: MapInfo.labelling), for the ledger.
    usage: UsageData = Field(default_factory=UsageData)


class MapBuildProgress(StageProgress):
    """A map build's stage (collecting frames, reconstructing region k of n, fusing the map, storing)."""

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

    job_id: SegmentId
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
