"""What the HTTP API returns, and how a job's record is folded from its events.

A mission's (or exploration's) record is *derived* from its event stream: :func:`apply_event` folds
one :class:`~shared.schemas.JobEvent` into a JSON-friendly summary that the store keeps beside the
events, so ``GET /missions/{id}`` is one row read and is the same after a gateway restart. Each event
kind carries its typed payload (:data:`shared.schemas.EventData`), so the fold is one case per payload.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from pydantic import BaseModel, Field

from shared.schemas import (
    ExplorationFinished, ExplorationProgress, ExplorationStarted, JobCancelled, JobFailed, JobEvent, JobEventKind,
    MissionEnd, MissionFinished, MissionStarted, JobState, MissionStep, Pose,
)

TERMINAL = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED})
# The states an event of each kind can carry; anything else is refused at ingest.
KIND_STATES = {
    JobEventKind.STARTED: frozenset({JobState.QUEUED, JobState.RUNNING}),
    JobEventKind.STEP: frozenset({JobState.RUNNING}),
    JobEventKind.PROGRESS: frozenset({JobState.QUEUED, JobState.RUNNING}),
    JobEventKind.FINISHED: TERMINAL,
    JobEventKind.ERROR: frozenset({JobState.FAILED}),
}
MAX_DECISIONS_KEPT = 1000  # a record stays small enough to serve 200 pollers; events keep everything


class JobKind(StrEnum):
    MISSION = "mission"
    EXPLORATION = "exploration"


# How a mission ended: the planner says it on MissionFinished; cancelled and failed come from their own
# events (or from the gateway, for a job it ended itself).
MissionOutcome = MissionEnd


def outcome_of(state: JobState, outcome: str | None) -> str | None:
    """The folded outcome, or the one a terminal state implies when no event said more (a job ended
    by the gateway itself)."""
    if outcome is not None:
        return outcome
    return {JobState.CANCELLED: MissionOutcome.CANCELLED.value,
            JobState.FAILED: MissionOutcome.FAILED.value}.get(state)


# --- folding -------------------------------------------------------------------------------------


def empty_summary() -> dict[str, Any]:
    return {"trajectory": [], "decisions": [], "metrics": None, "prompt_tokens": 0, "completion_tokens": 0,
            "cost_usd": 0.0, "progress": None, "stage": None, "message": None, "error": None,
            "map_id": None, "images": {}, "started_s": None, "finished_s": None, "last_step_seq": None,
            "candidates": [], "pose": None, "outcome": None, "success": None}


def _set_pose(summary: dict[str, Any], pose: Pose) -> None:
    xyz = [float(v) for v in pose.position_m]
    summary["pose"] = {"position_m": xyz, "heading_rad": float(pose.heading_rad)}
    # The trajectory is the sequence of distinct positions (a turn in place adds nothing).
    if not summary["trajectory"] or summary["trajectory"][-1] != xyz:
        summary["trajectory"].append(xyz)


def apply_event(summary: dict[str, Any], event: JobEvent, image_urls: dict[str, str]) -> dict[str, Any]:
    """Fold one event into ``summary`` (mutated and returned); ``image_urls`` name -> URL of its images.

    The payload was validated against its kind's schema when the event was decoded, so each case reads
    typed fields; there is nothing to guess."""
    if event.kind == "started" and summary["started_s"] is None:
        summary["started_s"] = event.timestamp_s
    if event.state in TERMINAL:
        summary["finished_s"] = event.timestamp_s
    d = event.data
    match d:
        case MissionStarted():
            _set_pose(summary, d.pose)
            summary["map_id"] = d.map_id
        case MissionStep():
            _set_pose(summary, d.pose)
            summary["candidates"] = [c.model_dump(mode="json") for c in d.candidates]
            dec = d.decision
            summary["decisions"].append({
                "step": event.step, "seq": event.seq, "candidate_index": dec.candidate_index, "kind": dec.kind.value,
                "reasoning": dec.reasoning, "backend": dec.backend, "fallback": dec.fallback})
            del summary["decisions"][:-MAX_DECISIONS_KEPT]
            summary["prompt_tokens"] += dec.prompt_tokens
            summary["completion_tokens"] += dec.completion_tokens
            summary["cost_usd"] += dec.cost_usd
        case MissionFinished():
            # The planner's word (the schema checked it against stop_called and the metrics).
            summary["outcome"] = d.outcome.value
            summary["success"] = d.success
            if d.metrics is not None:
                summary["metrics"] = d.metrics.model_dump(mode="json")
            if d.error:
                summary["error"] = d.error
            elif d.reason:
                summary["message"] = d.reason
        case ExplorationStarted():
            summary["map_id"] = d.map_id
        case ExplorationProgress():
            summary["progress"], summary["stage"] = d.progress, d.stage
            summary["message"] = d.message or summary["message"]
        case ExplorationFinished():
            summary["progress"], summary["stage"], summary["map_id"] = d.progress, d.stage, d.map_id
            # The map's labelling (the reconstructor's MLLM labeller) is this job's cost, as a mission's
            # decisions are the mission's.
            summary["prompt_tokens"] += d.usage.prompt_tokens
            summary["completion_tokens"] += d.usage.completion_tokens
            summary["cost_usd"] += d.usage.cost_usd
            summary["message"] = f"map {d.map_id} v{d.version}: {d.points} points from {d.regions} regions"
        case JobCancelled():
            summary["message"] = d.message
            summary["outcome"] = MissionOutcome.CANCELLED.value
            summary["stage"] = d.stage or summary["stage"]  # the stage it was stopped in
        case JobFailed():
            summary["error"] = d.error
            summary["outcome"] = MissionOutcome.FAILED.value
    if event.state == JobState.SUCCEEDED and summary.get("progress") is not None:
        summary["progress"] = 1.0
    if image_urls:
        summary["images"].update(image_urls)
        if event.kind == "step":
            summary["last_step_seq"] = event.seq
    return summary


# --- API models ----------------------------------------------------------------------------------


class JobCreated(BaseModel):
    id: str
    state: JobState
    url: str = Field(description="where to poll the job")
    events_url: str = Field(description="its Server-Sent Events stream")


class DecisionRecord(BaseModel):
    step: int
    seq: int
    candidate_index: int | None = None
    kind: str | None = None
    reasoning: str = ""
    backend: str = ""
    fallback: bool = False


class PoseRecord(BaseModel):
    position_m: list[float]
    heading_rad: float = 0.0


class JobRecord(BaseModel):
    id: str
    kind: JobKind
    state: JobState
    step: int
    last_seq: int = Field(description="seq of the newest stored event (-1: none yet)")
    created_s: float
    updated_s: float
    started_s: float | None = None
    finished_s: float | None = None
    error: str | None = None
    message: str | None = None
    images: dict[str, str] = Field(default_factory=dict, description="name -> URL of the latest image")
    url: str
    events_url: str


class MissionRecord(JobRecord):
    instruction: str
    map_id: str
    options: dict[str, Any]
    pose: PoseRecord | None = None
    trajectory: list[list[float]] = Field(default_factory=list, description="visited positions (x, y, z) m")
    candidates: list[dict[str, Any]] = Field(default_factory=list, description="the latest step's candidates")
    decisions: list[DecisionRecord] = Field(default_factory=list)
    outcome: MissionOutcome | None = Field(None, description="how it ended (None while it runs)")
    success: bool | None = Field(None, description="whether it reached its goal; None without a goal")
    metrics: dict[str, Any] | None = Field(None, description="VLN-CE metrics when the episode has a goal")
    prompt_tokens: int = 0
    completion_tokens: int = 0
    cost_usd: float = 0.0


class ExplorationRecord(JobRecord):
    map_id: str | None = Field(None, description="the map this exploration builds")
    progress: float | None = Field(None, ge=0, le=1)
    stage: str | None = None
    request: dict[str, Any] = Field(default_factory=dict)
    prompt_tokens: int = Field(0, description="what naming the map's rooms cost (the MLLM labeller), like a mission's")
    completion_tokens: int = 0
    cost_usd: float = 0.0


class MissionSummary(BaseModel):
    id: str
    state: JobState
    outcome: MissionOutcome | None = None
    success: bool | None = None
    step: int
    instruction: str
    map_id: str
    created_s: float
    updated_s: float
    url: str


class MissionPage(BaseModel):
    items: list[MissionSummary]
    total: int
    limit: int
    offset: int


class ExplorationPage(BaseModel):
    items: list[ExplorationRecord]
    total: int
    limit: int
    offset: int


class EventRecord(BaseModel):
    """One event as the API shows it: images by URL, never inline."""

    mission_id: str
    seq: int
    kind: str
    state: JobState
    step: int
    timestamp_s: float
    data: dict[str, Any]
    images: dict[str, str] = Field(default_factory=dict)
