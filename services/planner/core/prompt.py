"""The sub-path selection prompt in the paper's form, the answer format and its parser.

A :class:`Prompt` is an ordered list of text and image parts (backend-neutral). It renders to OpenAI
chat-completions messages (images as data URLs), hashes deterministically (the replay cache key) and
saves to a folder (``prompt.md`` + ``messages.json`` + PNGs) for inspection.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from libs.scenegraph.text import scene_graph_text
from shared.schemas import CandidateKind

from .context import CandidateView, StepContext
from .errors import AnswerError
from .history import HistoryItem, turn_phrase

ANSWER_FORMAT = '{"action": <candidate number>, "reasoning": "<one or two sentences>"}'

SYSTEM_PROMPT = (
    "You are the navigation policy of a robot that follows natural-language instructions inside a "
    "building. At every step you see the instruction, a compressed history of what you saw and did, and "
    "the candidate sub-paths you can take now. Each candidate shows the view you currently observe in its "
    "direction and the action; where available it also shows the view you would partially see after "
    "taking it, anticipated from a 3D reconstruction of the building (black areas are unreconstructed, not "
    "obstacles; flat mid-grey areas are surfaces, such as walls, whose colour from this side was never seen). "
    "A top-down spatial map may show your trajectory (path), your position and the numbered "
    "candidates. Choose the candidate whose sub-path, together with the history, best follows the "
    "instruction. Choose 'go back' only if you went the wrong way, and 'stop' only when you have reached "
    "the place where the instruction ends.\n"
    f"Answer with exactly one JSON object and nothing else: {ANSWER_FORMAT}"
)


@dataclass(frozen=True)
class PromptImage:
    """An image part of a prompt (RGB uint8)."""

    tag: str
    rgb: np.ndarray


PromptPart = str | PromptImage


@dataclass(frozen=True)
class Prompt:
    """A complete step prompt: the system text and the user content as ordered parts."""

    system: str
    parts: list[PromptPart]
    candidate_indices: list[int]
    meta: dict = field(default_factory=dict)

    def images(self) -> list[PromptImage]:
        return [p for p in self.parts if isinstance(p, PromptImage)]

    def text(self) -> str:
        """The user content as text, images shown as ``<image:tag>`` placeholders."""
        return "".join(p if isinstance(p, str) else f"<image:{p.tag}>" for p in self.parts)

    def digest(self) -> str:
        """SHA-256 over the exact content (texts, image shapes and pixel bytes): the replay cache key."""
        h = hashlib.sha256()
        h.update(self.system.encode())
        for p in self.parts:
            if isinstance(p, str):
                h.update(b"T")
                h.update(p.encode())
            else:
                arr = np.ascontiguousarray(p.rgb)
                h.update(b"I")
                h.update(p.tag.encode())
                h.update(repr((arr.shape, arr.dtype.str)).encode())
                h.update(arr.tobytes())
        return h.hexdigest()

    def to_openai_messages(self, image_format: str = "png", jpeg_quality: int = 90, detail: str = "auto") -> list[dict]:
        """OpenAI chat-completions messages: a system message and one multimodal user message."""
        content: list[dict] = []
        for p in self.parts:
            if isinstance(p, str):
                if content and content[-1]["type"] == "text":
                    content[-1]["text"] += p
                else:
                    content.append({"type": "text", "text": p})
            else:
                url = image_data_url(p.rgb, image_format, jpeg_quality)
                content.append({"type": "image_url", "image_url": {"url": url, "detail": detail}})
        return [{"role": "system", "content": self.system}, {"role": "user", "content": content}]

    def save(self, folder: str | Path) -> Path:
        """Write the prompt for inspection: ``prompt.md`` (readable, images inline), ``messages.json``
        (the chat messages with images as file references) and ``images/*.png``."""
        folder = Path(folder)
        (folder / "images").mkdir(parents=True, exist_ok=True)
        md = ["# System\n\n", self.system, "\n\n# User\n\n"]
        content: list[dict] = []
        for k, p in enumerate(self.parts):
            if isinstance(p, str):
                md.append(p)
                content.append({"type": "text", "text": p})
            else:
                name = f"images/{k:03d}_{_safe(p.tag)}.png"
                ok, buf = cv2.imencode(".png", cv2.cvtColor(p.rgb, cv2.COLOR_RGB2BGR))
                if not ok:
                    raise OSError(f"could not encode image {p.tag}")
                (folder / name).write_bytes(buf.tobytes())
                md.append(f"![{p.tag}]({name})")
                content.append({"type": "image_file", "path": name, "tag": p.tag})
        (folder / "prompt.md").write_text("".join(md) + "\n")
        messages = [{"role": "system", "content": self.system}, {"role": "user", "content": content}]
        meta = {"digest": self.digest(), "candidate_indices": self.candidate_indices, **self.meta}
        (folder / "messages.json").write_text(json.dumps({"messages": messages, "meta": meta}, indent=2))
        return folder


def _safe(tag: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", tag)[:60]


def image_data_url(rgb: np.ndarray, image_format: str = "png", jpeg_quality: int = 90) -> str:
    """``data:image/...;base64,...`` for an RGB uint8 image."""
    bgr = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)
    if image_format == "png":
        ok, buf = cv2.imencode(".png", bgr)
        mime = "image/png"
    elif image_format in ("jpeg", "jpg"):
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        mime = "image/jpeg"
    else:
        raise ValueError(f"unknown image format {image_format!r}")
    if not ok:
        raise ValueError("image encoding failed")
    return f"data:{mime};base64,{base64.b64encode(buf.tobytes()).decode()}"


def describe_candidate(view: CandidateView) -> str:
    """The action text of a candidate, in agent-relative terms."""
    c = view.candidate
    if c.kind == CandidateKind.STOP:
        return "stop here"
    dist = c.distance_m or math.hypot(c.dx_m, c.dy_m)
    if c.kind == CandidateKind.BACKTRACK:
        return f"go back to the previous position ({dist:.1f} m away)"
    phrase = turn_phrase(c.angle_rad)
    if phrase == "go straight":
        return f"go straight {dist:.1f} m"
    return f"{phrase} and move {dist:.1f} m"


@dataclass(frozen=True)
class PromptConfig:
    """How the prompt is assembled."""

    max_history_items: int = 16  # the most recent items of the compressed stream
    image_px: int = 256  # candidate views are resized to this (history is already 256)
    scene_graph: bool = True  # the map's scene graph as text (issue 32), when the mission has one
    scene_graph_max_chars: int = 4000  # ~1,000 tokens: a big house is cut to the rooms nearest the agent


class PromptBuilder:
    """Builds the step prompt from a :class:`StepContext` (honouring its ablation flags)."""

    def __init__(self, config: PromptConfig | None = None):
        self.config = config or PromptConfig()

    def _img(self, rgb: np.ndarray) -> np.ndarray:
        px = self.config.image_px
        if rgb.shape[:2] == (px, px):
            return rgb
        return cv2.resize(rgb, (px, px), interpolation=cv2.INTER_AREA)

    def build(self, ctx: StepContext) -> Prompt:
        parts: list[PromptPart] = [f"Instruction: {ctx.instruction.strip()}\n\n"]
        parts += self._scene_graph(ctx)
        parts += self._history(ctx.history)
        parts.append(f"\nStep {ctx.step + 1} of at most {ctx.max_steps}. Candidate sub-paths:\n")
        for view in ctx.candidates:
            parts += self._candidate(ctx, view)
        if ctx.ablation.spatial_map and ctx.spatial_map_rgb is not None:
            parts.append(
                "\nSpatial map (top-down view of the reconstructed building; the line is your trajectory, "
                "the arrow is you, numbers are the candidates): "
            )
            parts.append(PromptImage("spatial_map", np.asarray(ctx.spatial_map_rgb)))
            parts.append("\n")
        indices = [c.index for c in ctx.candidates]
        parts.append(
            f"\nChoose one candidate number from {indices}. Answer with exactly one JSON object and "
            f"nothing else: {ANSWER_FORMAT}"
        )
        meta = {
            "mission_id": ctx.mission_id,
            "step": ctx.step,
            "anticipation": ctx.ablation.anticipation,
            "anticipation_hfov_deg": ctx.ablation.anticipation_hfov_deg,
            "spatial_map": ctx.ablation.spatial_map,
            "scene_graph": bool(self._scene_graph(ctx)),
        }
        return Prompt(system=SYSTEM_PROMPT, parts=parts, candidate_indices=indices, meta=meta)

    def _scene_graph(self, ctx: StepContext) -> list[PromptPart]:
        """The scene graph block (issue 32): the whole map's rooms, objects and openings, and where the
        agent is; nothing when switched off or when the mission has no graph."""
        if not self.config.scene_graph or ctx.scene_graph is None or not ctx.scene_graph.rooms:
            return []
        text = scene_graph_text(ctx.scene_graph, ctx.pose.position_m, self.config.scene_graph_max_chars)
        return [text + "\n\n"]

    def _history(self, history: list[HistoryItem]) -> list[PromptPart]:
        if not history:
            return ["History: this is the first step; nothing has happened yet.\n"]
        items = history[-self.config.max_history_items :]
        parts: list[PromptPart] = ["History (observations joined by the actions taken, oldest first):\n"]
        if len(items) < len(history):
            parts.append(f"(... {len(history) - len(items)} earlier items omitted ...)\n")
        for item in items:
            parts.append(f"[step {item.step + 1}] ")
            parts.append(PromptImage(f"history_step{item.step + 1}", item.image))
            if item.action is not None:
                parts.append(f" -> {item.action.describe()} ->\n")
            else:
                parts.append("\n")
        return parts

    def _candidate(self, ctx: StepContext, view: CandidateView) -> list[PromptPart]:
        c = view.candidate
        parts: list[PromptPart] = [f"Candidate {c.index}: "]
        if c.kind == CandidateKind.STOP:
            if view.observed_rgb is not None:
                parts += ["[observed view] ", PromptImage(f"cand{c.index}_observed", self._img(view.observed_rgb)), " "]
            parts.append("[action: stop here - the instruction's destination is reached]\n")
            return parts
        if view.observed_rgb is not None:
            parts += ["[observed view] ", PromptImage(f"cand{c.index}_observed", self._img(view.observed_rgb)), " "]
        parts.append(f"[action: {describe_candidate(view)}]")
        if ctx.ablation.anticipation and view.anticipated_rgb is not None:
            parts.append(" -> if I took this action, I would partially imagine the next view: ")
            parts.append(PromptImage(f"cand{c.index}_anticipated", self._img(view.anticipated_rgb)))
        parts.append("\n")
        return parts


# --- answers ------------------------------------------------------------------------------------------

_JSON_OBJECT = re.compile(r"\{.*\}", re.DOTALL)


def parse_answer(text: str | None, valid_indices: list[int]) -> tuple[int, str]:
    """Parse ``{"action": k, "reasoning": "..."}`` (code fences and surrounding prose tolerated).

    Returns (candidate index, reasoning); raises :class:`AnswerError` saying what is wrong, which the
    corrective re-ask quotes back to the model.
    """
    if not text or not text.strip():
        raise AnswerError("the answer was empty")
    m = _JSON_OBJECT.search(text)
    if not m:
        raise AnswerError("the answer contains no JSON object")
    try:
        obj = json.loads(m.group(0))
    except json.JSONDecodeError as exc:
        raise AnswerError(f"the JSON object is malformed ({exc.msg})") from None
    if not isinstance(obj, dict) or "action" not in obj:
        raise AnswerError('the JSON object has no "action" field')
    action = obj["action"]
    if isinstance(action, str):
        digits = re.search(r"-?\d+", action)
        if not digits:
            raise AnswerError(f'"action" must be a candidate number, got {action!r}')
        action = int(digits.group(0))
    if isinstance(action, bool) or not isinstance(action, (int, float)) or int(action) != action:
        raise AnswerError(f'"action" must be an integer candidate number, got {obj["action"]!r}')
    action = int(action)
    if action not in valid_indices:
        raise AnswerError(f'"action" {action} is not one of the candidates {valid_indices}')
    reasoning = obj.get("reasoning", "")
    return action, reasoning if isinstance(reasoning, str) else json.dumps(reasoning)


def corrective_message(error: AnswerError, valid_indices: list[int]) -> str:
    """The single re-ask sent after an invalid answer."""
    return (
        f"Your previous answer was invalid: {error}. Reply again with exactly one JSON object and nothing "
        f"else, choosing one of {valid_indices}: {ANSWER_FORMAT}"
    )
