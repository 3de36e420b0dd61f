"""What the HTTP API returns, and how a job's record is folded from its events.

A mission's (or exploration's) record is *derived* from its event stream: :func:`apply_event` folds
one :class:`~shared.schemas.MissionEvent` into a JSON-friendly summary that the store keeps beside the
events, so ``GET /missions/{id}`` is one row read and is the same after a gateway restart. The fold is
lenient about ``data``: planners may leave fields out, and an odd value is skipped, never an error.

Expected ``data`` fields (all optional): ``pose`` ({position_m, heading_rad}), ``candidates`` (list of
Candidate dicts), ``decision`` (Decision dict with ``reasoning``), ``reasoning``, ``timings_s``,
``metrics`` (VLN-CE: ne_m, sr, spl, ...), ``prompt_tokens``/``completion_tokens``/``cost_usd`` (or inside
``decision``), ``progress`` (0-1), ``stage``, ``message``, ``map_id``, ``error``.
"""

from __future__ import annotations

import math
from enum import StrEnum
from typing import Any

from pydantic import BaseModel, Field

from shared.schemas import MissionEvent, MissionEventKind, MissionState

TERMINAL = frozenset({MissionState.SUCCEEDED, MissionState.FAILED, MissionState.CANCELLED})
# The states an event of each kind can carry; anything else is refused at ingest.
KIND_STATES = {
    MissionEventKind.STARTED: frozenset({MissionState.QUEUED, MissionState.RUNNING}),
    MissionEventKind.STEP: frozenset({MissionState.RUNNING}),
    MissionEventKind.PROGRESS: frozenset({MissionState.QUEUED, MissionState.RUNNING}),
    MissionEventKind.FINISHED: TERMINAL,
    MissionEventKind.ERROR: frozenset({MissionState.FAILED}),
}
MAX_DECISIONS_KEPT = 1000  # a record stays small enough to serve 200 pollers; events keep everything


class JobKind(StrEnum):
    MISSION = "mission"
    EXPLORATION = "exploration"


# --- folding -------------------------------------------------------------------------------------


def _xyz(value: Any) -> list[float] | None:
    if isinstance(value, dict):
        value = value.get("position_m")
    if isinstance(value, (list, tuple)) and len(value) == 3:
        try:
            out = [float(v) for v in value]
        except (TypeError, ValueError):
            return None
        return out if all(math.isfinite(v) for v in out) else None
    return None


def _num(value: Any, default: float = 0.0) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return default
    return out if math.isfinite(out) else default


def empty_summary() -> dict[str, Any]:
    return {"trajectory": [], "decisions": [], "metrics": None, "prompt_tokens": 0, "completion_tokens": 0,
            "cost_usd": 0.0, "progress": None, "stage": None, "message": None, "error": None,
            "map_id": None, "images": {}, "started_s": None, "finished_s": None, "last_step_seq": None,
            "candidates": [], "pose": None}


def apply_event(summary: dict[str, Any], event: MissionEvent, image_urls: dict[str, str]) -> dict[str, Any]:
    """Fold one event into ``summary`` (mutated and returned); ``image_urls`` name -> URL of its images."""
    data = event.data if isinstance(event.data, dict) else {}
    if event.kind == "started" and summary["started_s"] is None:
        summary["started_s"] = event.timestamp_s
    if event.state in TERMINAL:
        summary["finished_s"] = event.timestamp_s
    pose = data.get("pose")
    xyz = _xyz(pose)
    if xyz is not None:
        summary["pose"] = {"position_m": xyz, "heading_rad": _num(pose.get("heading_rad"))
                           if isinstance(pose, dict) else 0.0}
        # The trajectory is the sequence of distinct positions (a turn in place adds nothing).
        if not summary["trajectory"] or summary["trajectory"][-1] != xyz:
            summary["trajectory"].append(xyz)
    if isinstance(data.get("candidates"), list):
        summary["candidates"] = [c for c in data["candidates"] if isinstance(c, dict)]
    decision = data.get("decision")
    if isinstance(decision, dict):
        entry = {"step": event.step, "seq": event.seq,
                 "candidate_index": decision.get("candidate_index"), "kind": decision.get("kind"),
                 "reasoning": decision.get("reasoning") or data.get("reasoning") or "",
                 "backend": decision.get("backend", ""), "fallback": bool(decision.get("fallback", False))}
        summary["decisions"].append(entry)
        del summary["decisions"][:-MAX_DECISIONS_KEPT]
        for key in ("prompt_tokens", "completion_tokens"):
            summary[key] += int(_num(decision.get(key)))
        summary["cost_usd"] += _num(decision.get("cost_usd"))
    else:
        for key in ("prompt_tokens", "completion_tokens"):
            summary[key] += int(_num(data.get(key)))
        summary["cost_usd"] += _num(data.get("cost_usd"))
    if isinstance(data.get("metrics"), dict):
        summary["metrics"] = {k: v for k, v in data["metrics"].items() if isinstance(v, (int, float, str, bool))}
    if "progress" in data:
        summary["progress"] = min(1.0, max(0.0, _num(data["progress"])))
    for key in ("stage", "message", "map_id"):
        if isinstance(data.get(key), str):
            summary[key] = data[key]
    if event.kind == "error" or isinstance(data.get("error"), str):
        summary["error"] = str(data.get("error") or data.get("message") or "error")
    if event.state == MissionState.SUCCEEDED and summary.get("progress") is not None:
        summary["progress"] = 1.0
    if image_urls:
        summary["images"].update(image_urls)
        if event.kind == "step":
            summary["last_step_seq"] = event.seq
    return summary


# --- API models ----------------------------------------------------------------------------------


class JobCreated(BaseModel):
    id: str
    state: MissionState
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
    state: MissionState
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
    metrics: dict[str, Any] | None = Field(None, description="VLN-CE metrics when the episode has a goal")
    prompt_tokens: int = 0
    completion_tokens: int = 0
    cost_usd: float = 0.0


class ExplorationRecord(JobRecord):
    map_id: str | None = Field(None, description="the map this exploration builds")
    progress: float | None = Field(None, ge=0, le=1)
    stage: str | None = None
    request: dict[str, Any] = Field(default_factory=dict)


class MissionSummary(BaseModel):
    id: str
    state: MissionState
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
    state: MissionState
    step: int
    timestamp_s: float
    data: dict[str, Any]
    images: dict[str, str] = Field(default_factory=dict)
