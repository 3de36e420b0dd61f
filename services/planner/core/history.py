"""Compressed visual history (paper Sec. 4.3, "Compressed History Streams").

The history is a stream of observations joined by the actions taken. Long runs of forward moves are
redundant, so consecutive forward moves are merged into one action and only the observations at the
start and the end of the run are kept; every kept image is resized to 256x256.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import cv2
import numpy as np

from shared.schemas import Candidate, CandidateKind

HISTORY_IMAGE_PX = 256
FORWARD_TOLERANCE_DEG = 20.0  # a move whose direction is within this of the heading counts as "forward"


class ActionKind(StrEnum):
    FORWARD = "forward"
    TURN_MOVE = "turn_move"
    BACKTRACK = "backtrack"
    STOP = "stop"


@dataclass(frozen=True)
class ActionRecord:
    """One executed action, described in agent-relative terms."""

    kind: ActionKind
    angle_rad: float = 0.0  # relative to the heading before the action, positive = left
    distance_m: float = 0.0
    moves: int = 1  # > 1 once consecutive forward moves are merged

    def describe(self) -> str:
        """Plain-language description used in prompts (and by humans reading saved prompts)."""
        if self.kind == ActionKind.STOP:
            return "stop"
        if self.kind == ActionKind.BACKTRACK:
            return f"go back to the previous position ({self.distance_m:.1f} m)"
        if self.kind == ActionKind.FORWARD:
            if self.moves > 1:
                return f"move forward {self.distance_m:.1f} m ({self.moves} moves)"
            return f"move forward {self.distance_m:.1f} m"
        return f"{turn_phrase(self.angle_rad)} and move forward {self.distance_m:.1f} m"


def turn_phrase(angle_rad: float) -> str:
    """'turn left 60 degrees' / 'turn right 90 degrees' / 'turn around' / 'go straight'."""
    deg = math.degrees(angle_rad)
    mag = abs(deg)
    if mag < FORWARD_TOLERANCE_DEG:
        return "go straight"
    if mag >= 165.0:
        return "turn around"
    return f"turn {'left' if deg > 0 else 'right'} {mag:.0f} degrees"


def action_for(candidate: Candidate) -> ActionRecord:
    """The :class:`ActionRecord` of executing ``candidate``."""
    if candidate.kind == CandidateKind.STOP:
        return ActionRecord(ActionKind.STOP)
    dist = candidate.distance_m or math.hypot(candidate.dx_m, candidate.dy_m)
    if candidate.kind == CandidateKind.BACKTRACK:
        return ActionRecord(ActionKind.BACKTRACK, candidate.angle_rad, dist)
    if abs(math.degrees(candidate.angle_rad)) < FORWARD_TOLERANCE_DEG:
        return ActionRecord(ActionKind.FORWARD, candidate.angle_rad, dist)
    return ActionRecord(ActionKind.TURN_MOVE, candidate.angle_rad, dist)


@dataclass(frozen=True)
class HistoryItem:
    """One element of the compressed stream: an observation image followed by the action taken from it.

    ``action`` is None for a trailing observation (the end of a forward run that reaches the present).
    """

    step: int
    image: np.ndarray  # (256, 256, 3) uint8
    action: ActionRecord | None


def resize_for_history(rgb: np.ndarray, size_px: int = HISTORY_IMAGE_PX) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"history images must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if rgb.shape[:2] == (size_px, size_px):
        return rgb
    # INTER_AREA: the right filter for downscaling camera images without aliasing.
    return cv2.resize(rgb, (size_px, size_px), interpolation=cv2.INTER_AREA)


class HistoryRecorder:
    """Records (observation, action) per executed step; :meth:`compressed` gives the paper's stream."""

    def __init__(self, size_px: int = HISTORY_IMAGE_PX):
        self.size_px = size_px
        self._steps: list[tuple[int, np.ndarray, ActionRecord]] = []

    def __len__(self) -> int:
        return len(self._steps)

    def clear(self) -> None:
        self._steps.clear()

    def record(self, step: int, observation_rgb: np.ndarray, action: ActionRecord) -> None:
        """Record the forward view seen at ``step`` (before acting) and the action then taken."""
        self._steps.append((step, resize_for_history(observation_rgb, self.size_px), action))

    def raw(self) -> list[HistoryItem]:
        return [HistoryItem(s, img, a) for s, img, a in self._steps]

    def compressed(self, current_rgb: np.ndarray | None = None, current_step: int | None = None) -> list[HistoryItem]:
        """The compressed stream.

        A run of consecutive forward moves ``o_i a_i o_{i+1} ... a_j o_{j+1}`` becomes
        ``o_i [forward, summed distance, j-i+1 moves] o_{j+1}``. When the run reaches the present, its end
        observation is ``current_rgb`` if given (the prompt shows the current views separately otherwise).
        """
        return compress(self.raw(), current_rgb=current_rgb, current_step=current_step, size_px=self.size_px)


def compress(
    items: list[HistoryItem],
    current_rgb: np.ndarray | None = None,
    current_step: int | None = None,
    size_px: int = HISTORY_IMAGE_PX,
) -> list[HistoryItem]:
    """Merge consecutive forward moves of a raw (observation, action) stream; see :class:`HistoryRecorder`."""
    out: list[HistoryItem] = []
    i, n = 0, len(items)
    while i < n:
        item = items[i]
        if item.action is None or item.action.kind != ActionKind.FORWARD:
            out.append(item)
            i += 1
            continue
        j = i
        while j + 1 < n and items[j + 1].action is not None and items[j + 1].action.kind == ActionKind.FORWARD:
            j += 1
        if j == i:
            out.append(item)
        else:
            run = items[i : j + 1]
            merged = ActionRecord(
                ActionKind.FORWARD,
                angle_rad=0.0,
                distance_m=float(sum(r.action.distance_m for r in run)),
                moves=sum(r.action.moves for r in run),
            )
            out.append(HistoryItem(item.step, item.image, merged))
            if j + 1 >= n and current_rgb is not None:
                step = current_step if current_step is not None else items[j].step + 1
                out.append(HistoryItem(step, resize_for_history(current_rgb, size_px), None))
        i = j + 1
    return out
