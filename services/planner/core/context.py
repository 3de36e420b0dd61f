"""The step context: everything a policy may look at to choose one sub-path.

Every backend (openai, heuristic, replay, oracle) consumes the same :class:`StepContext`, built once per
step by the mission loop from robot-io's panorama, the waypoint predictor's candidates, the renderer's
anticipated views and spatial map, and the compressed history. Evaluation-only knowledge (goal, reference
path, geodesic) travels in :class:`OracleInfo` and never reaches a prompt.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from shared.geometry import wrap_angle
from shared.schemas import Candidate, CandidateKind, Panorama, Pose, RenderResult, SceneGraph

from .errors import ContextError
from .history import HistoryItem


@dataclass(frozen=True)
class Ablation:
    """The paper's ablations as configuration (Tables III/IV)."""

    anticipation: bool = True
    anticipation_hfov_deg: float = 90.0
    spatial_map: bool = True

    def __post_init__(self) -> None:
        if not 30.0 <= self.anticipation_hfov_deg <= 150.0:
            raise ContextError(f"anticipation_hfov_deg must be in [30, 150], got {self.anticipation_hfov_deg}")


@dataclass
class CandidateView:
    """One candidate sub-path with what the agent sees towards it and what it anticipates there.

    Images are (H, W, 3) uint8 RGB; labels (H, W) int32 class ids with -1 = unknown; depth (H, W)
    float32 z-depth with 0 = no measurement.
    """

    candidate: Candidate
    observed_rgb: np.ndarray | None = None
    observed_labels: np.ndarray | None = None
    observed_depth_m: np.ndarray | None = None
    observed_view_index: int | None = None
    anticipated_rgb: np.ndarray | None = None
    anticipated_labels: np.ndarray | None = None
    anticipated_depth_m: np.ndarray | None = None
    anticipated_hole_fraction: float | None = None

    @property
    def index(self) -> int:
        return self.candidate.index

    @property
    def kind(self) -> CandidateKind:
        return self.candidate.kind


GeodesicFn = Callable[[np.ndarray, np.ndarray], "float | None"]


@dataclass
class OracleInfo:
    """Evaluation-only ground truth; the oracle policy needs it, prompts never see it."""

    goal_m: np.ndarray
    reference_path_m: np.ndarray | None = None
    geodesic: GeodesicFn | None = None


@dataclass
class StepContext:
    """What every policy backend receives at one step of a mission."""

    instruction: str
    step: int
    pose: Pose
    candidates: list[CandidateView]
    trajectory_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    history: list[HistoryItem] = field(default_factory=list)
    spatial_map_rgb: np.ndarray | None = None
    label_names: dict[int, str] = field(default_factory=dict)
    ablation: Ablation = field(default_factory=Ablation)
    mission_id: str = ""
    max_steps: int = 40
    panorama: Panorama | None = None  # the current observation, for policies that look around
    oracle: OracleInfo | None = None
    scene_graph: SceneGraph | None = None  # the map's scene graph (issue 32), fetched once per mission

    def __post_init__(self) -> None:
        if not self.candidates:
            raise ContextError("a step needs at least one candidate (stop is always possible)")
        indices = [c.index for c in self.candidates]
        if len(set(indices)) != len(indices):
            raise ContextError(f"candidate indices must be unique, got {indices}")
        self.trajectory_m = np.asarray(self.trajectory_m, dtype=np.float64).reshape(-1, 3)

    def candidate(self, index: int) -> CandidateView:
        for c in self.candidates:
            if c.index == index:
                return c
        raise ContextError(f"no candidate with index {index}; have {[c.index for c in self.candidates]}")

    def by_kind(self, kind: CandidateKind) -> list[CandidateView]:
        return [c for c in self.candidates if c.kind == kind]

    @property
    def stop_candidate(self) -> CandidateView | None:
        stops = self.by_kind(CandidateKind.STOP)
        return stops[0] if stops else None

    def target_m(self, view: CandidateView) -> np.ndarray:
        """Absolute floor position a candidate leads to (the current position for stop)."""
        p = self.pose.xyz.copy()
        p[0] += view.candidate.dx_m
        p[1] += view.candidate.dy_m
        return p


def candidate_world_heading(pose: Pose, cand: Candidate) -> float:
    """World heading towards a candidate: from (dx, dy) when it moves, else from its relative angle."""
    if math.hypot(cand.dx_m, cand.dy_m) > 1e-6:
        return math.atan2(cand.dy_m, cand.dx_m)
    return float(wrap_angle(pose.heading_rad + cand.angle_rad))


def nearest_view_index(headings_rad: np.ndarray, heading_rad: float) -> int:
    """Index of the panorama view whose heading is closest to ``heading_rad``."""
    diff = np.abs(wrap_angle(np.asarray(headings_rad, dtype=np.float64) - heading_rad))
    return int(np.argmin(diff))


def with_stop_and_backtrack(
    waypoints: Sequence[Candidate], pose: Pose, previous_position_m: Sequence[float] | None
) -> list[Candidate]:
    """Re-index predictor waypoints 0..K-1 and append an explicit backtrack (when there is a previous
    node) and a stop candidate, so every step offers the paper's full action space."""
    out: list[Candidate] = []
    for cand in waypoints:
        if cand.kind != CandidateKind.WAYPOINT:
            continue
        out.append(cand.model_copy(update={"index": len(out)}))
    if previous_position_m is not None:
        dx = float(previous_position_m[0]) - pose.position_m[0]
        dy = float(previous_position_m[1]) - pose.position_m[1]
        dist = math.hypot(dx, dy)
        if dist > 1e-3:
            rel = float(wrap_angle(math.atan2(dy, dx) - pose.heading_rad))
            out.append(
                Candidate(
                    index=len(out), kind=CandidateKind.BACKTRACK, dx_m=dx, dy_m=dy, angle_rad=rel, distance_m=dist
                )
            )
    out.append(Candidate(index=len(out), kind=CandidateKind.STOP))
    return out


def build_candidate_views(
    candidates: Sequence[Candidate],
    panorama: Panorama | None,
    render: RenderResult | None = None,
    render_rows: Mapping[int, int] | None = None,
) -> list[CandidateView]:
    """Pair every candidate with its observed view and (when rendered) its anticipated view.

    Args:
        candidates: the step's candidates (waypoints, backtrack, stop).
        panorama: the current observation; the observed view of a candidate is the panorama view whose
            heading is nearest the candidate's direction (stop: the forward view).
        render: the renderer's anticipated views (None: anticipation off).
        render_rows: candidate index -> row of ``render``; by default waypoint and backtrack candidates in
            their order in ``candidates``.
    """
    if render is not None and render_rows is None:
        movable = [c.index for c in candidates if c.kind != CandidateKind.STOP]
        render_rows = {idx: row for row, idx in enumerate(movable)}
    views: list[CandidateView] = []
    for cand in candidates:
        v = CandidateView(candidate=cand)
        if panorama is not None:
            if cand.kind == CandidateKind.STOP:
                i = nearest_view_index(panorama.headings_rad, panorama.pose.heading_rad)
            else:
                i = nearest_view_index(panorama.headings_rad, candidate_world_heading(panorama.pose, cand))
            v.observed_view_index = i
            v.observed_rgb = panorama.rgb[i]
            v.observed_depth_m = panorama.depth_m[i]
            v.observed_labels = None if panorama.semantic is None else panorama.semantic[i]
        if render is not None and render_rows is not None and cand.index in render_rows:
            row = render_rows[cand.index]
            if not 0 <= row < render.rgb.shape[0]:
                raise ContextError(f"render row {row} out of range for {render.rgb.shape[0]} views")
            v.anticipated_rgb = render.rgb[row]
            v.anticipated_depth_m = render.depth_m[row]
            v.anticipated_labels = None if render.labels is None else render.labels[row]
            v.anticipated_hole_fraction = float(render.hole_mask[row].mean())
        views.append(v)
    return views
