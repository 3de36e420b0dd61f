"""Missions and explorations: requests, decisions, job states."""

from __future__ import annotations

import unicodedata
from enum import StrEnum
from typing import Annotated, Any, ClassVar, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator

from .base import SegmentId, _free_form_check, Cost_usd, Count, FREE_FORM_MAX_ITEMS, Message, PATH_MAX_POINTS, Xyz_m
from .geometry import Pose
from .navigation import CandidateKind
from .render import SplatMode


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
    # What a VLM server was sent and said beyond the action: the prompt's layout and what the context
    # budget dropped ("history frames 16->4"), and a reasoning model's <think> text (kept, never parsed).
    prompt_notes: str = Field("", max_length=2000)
    thinking: str = Field("", max_length=20_000)


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
    mission_id: SegmentId
    instruction: Instruction
    map_id: SegmentId
    options: MissionOptions = Field(default_factory=MissionOptions)


class JobAccepted(Message):
    """A job's submission answered: accepted (its events follow on its events key) or refused, with why."""

    job_id: SegmentId
    accepted: bool
    reason: str = ""
    instance: str = ""  # the worker instance that took the job ("" : not said; the gateway then looks it up)


class CancelRequest(Message):
    mission_id: SegmentId


class JobEventKind(StrEnum):
    STARTED = "started"
    STEP = "step"
    PROGRESS = "progress"
    FINISHED = "finished"
    ERROR = "error"


class ExplorationRequest(Message):
    """Pre-explore the robot's current scene, record tours and reconstruct a map named ``map_id``."""

    exploration_id: SegmentId
    map_id: SegmentId
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

    exploration_id: SegmentId
