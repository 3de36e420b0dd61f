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
from .image_tokens import image_tokens_by
from .layout import LAYOUTS, Layout, Tile, best_columns, cap_side, fit, mosaic, stack

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

    def to_openai_messages(self, image_format: str = "png", jpeg_quality: int = 90,
                           detail: str | None = "auto") -> list[dict]:
        """OpenAI chat-completions messages: a system message and one multimodal user message
        (``detail`` None: the field is left out, for servers that do not take it)."""
        content: list[dict] = []
        for p in self.parts:
            if isinstance(p, str):
                if content and content[-1]["type"] == "text":
                    content[-1]["text"] += p
                else:
                    content.append({"type": "text", "text": p})
            else:
                url = image_data_url(p.rgb, image_format, jpeg_quality)
                image_url = {"url": url} if detail is None else {"url": url, "detail": detail}
                content.append({"type": "image_url", "image_url": image_url})
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
    """How the prompt is assembled.

    ``layout``: ``separate`` (one image per view, the paper's form), ``mosaic`` (one numbered composite
    per kind, see :mod:`.layout`) or ``auto`` (separate while its images fit ``max_images_per_prompt``,
    else mosaic). A mosaic that still has more images than the limit becomes one stacked panel.
    ``max_history_frames`` keeps the images of only the most recent history items; the older ones keep
    their action text (cheap, and what the history is for). ``max_image_px`` caps every image's longer
    side (servers resize or refuse larger ones).
    """

    max_history_items: int = 16  # the most recent items of the compressed stream
    image_px: int = 256  # candidate views are resized to this (history is already 256)
    layout: Layout = "separate"
    max_images_per_prompt: int | None = None  # None: no limit
    max_image_px: int | None = None  # None: no limit
    max_history_frames: int | None = None  # None: every history item shows its image
    # The server's image-token rule (tokens.IMAGE_TOKEN_RULES): a mosaic's columns are chosen to cost the
    # fewest tokens by it.
    image_token_rule: str = "openai_tiles"
    scene_graph: bool = True  # the map's scene graph as text (issue 32), when the mission has one
    scene_graph_max_chars: int = 4000  # ~1,000 tokens: a big house is cut to the rooms nearest the agent

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {self.layout!r}")
        if not 16 <= self.image_px <= 2048:
            raise ValueError(f"image_px must be in [16, 2048], got {self.image_px}")
        if self.max_images_per_prompt is not None and not 1 <= self.max_images_per_prompt <= 10_000:
            raise ValueError(f"max_images_per_prompt must be in [1, 10000], got {self.max_images_per_prompt}")
        if self.max_image_px is not None and not 16 <= self.max_image_px <= 8192:
            raise ValueError(f"max_image_px must be in [16, 8192], got {self.max_image_px}")
        if self.max_history_frames is not None and not 0 <= self.max_history_frames <= 1000:
            raise ValueError(f"max_history_frames must be in [0, 1000], got {self.max_history_frames}")
        if not 0 <= self.max_history_items <= 1000:
            raise ValueError(f"max_history_items must be in [0, 1000], got {self.max_history_items}")

    def describe(self) -> str:
        """One line for records and cache keys: every field that changes what is sent."""
        return (f"layout={self.layout} image_px={self.image_px} max_image_px={self.max_image_px} "
                f"max_images={self.max_images_per_prompt} history_items={self.max_history_items} "
                f"history_frames={self.max_history_frames} image_rule={self.image_token_rule} "
                f"scene_graph={self.scene_graph}:{self.scene_graph_max_chars}")


class PromptBuilder:
    """Builds the step prompt from a :class:`StepContext` (honouring its ablation flags).

    Sections (instruction, history, candidates, spatial map, answer request) are separate methods that
    return parts, so that a new block (a scene graph, say) is one more method and one more line in
    :meth:`build`. In the mosaic layout a section names its tiles in text and hands its views to the
    composite that :meth:`build` places after the section.
    """

    def __init__(self, config: PromptConfig | None = None):
        self.config = config or PromptConfig()

    def _img(self, rgb: np.ndarray, cfg: PromptConfig | None = None) -> np.ndarray:
        cfg = cfg or self.config
        px = cfg.image_px if cfg.max_image_px is None else min(cfg.image_px, cfg.max_image_px)
        return fit(rgb, px)

    def separate_image_count(self, ctx: StepContext, cfg: PromptConfig | None = None) -> int:
        """How many images the ``separate`` layout would send for ``ctx``."""
        cfg = cfg or self.config
        items = ctx.history[-cfg.max_history_items :] if cfg.max_history_items else []
        n = len(items) if cfg.max_history_frames is None else min(len(items), cfg.max_history_frames)
        for view in ctx.candidates:
            n += view.observed_rgb is not None
            n += (view.kind != CandidateKind.STOP and ctx.ablation.anticipation and view.anticipated_rgb is not None)
        return n + bool(ctx.ablation.spatial_map and ctx.spatial_map_rgb is not None)

    def resolve_layout(self, ctx: StepContext, cfg: PromptConfig | None = None) -> str:
        """``separate`` or ``mosaic`` for this step (``auto`` picks by the image budget)."""
        cfg = cfg or self.config
        if cfg.layout != "auto":
            return cfg.layout
        limit = cfg.max_images_per_prompt
        return "separate" if limit is None or self.separate_image_count(ctx, cfg) <= limit else "mosaic"

    def build(self, ctx: StepContext, config: PromptConfig | None = None) -> Prompt:
        cfg = config or self.config
        layout = self.resolve_layout(ctx, cfg)
        tiles: dict[str, list[Tile]] | None = {"history": [], "candidates": []} if layout == "mosaic" else None
        parts: list[PromptPart] = [f"Instruction: {ctx.instruction.strip()}\n\n"]
        parts += self._scene_graph(ctx, cfg)
        parts += self._history(ctx.history, cfg, tiles)
        if tiles is not None and tiles["history"]:
            parts += ["History tiles (numbered by step): ",
                      PromptImage("history_mosaic", self._mosaic(tiles["history"], cfg)),
                      "\n"]
        parts.append(f"\nStep {ctx.step + 1} of at most {ctx.max_steps}. Candidate sub-paths:\n")
        for view in ctx.candidates:
            parts += self._candidate(ctx, view, cfg, tiles)
        if tiles is not None and tiles["candidates"]:
            parts += ["Candidate views (cell k shows candidate k: the observed view above, the anticipated "
                      "view below; a black tile is a view not available): ",
                      PromptImage("candidates_mosaic", self._mosaic(tiles["candidates"], cfg)),
                      "\n"]
        parts += self._spatial_map(ctx, cfg)
        indices = [c.index for c in ctx.candidates]
        parts.append(
            f"\nChoose one candidate number from {indices}. Answer with exactly one JSON object and "
            f"nothing else: {ANSWER_FORMAT}"
        )
        if layout == "mosaic" and cfg.max_images_per_prompt is not None:
            parts = _as_panel(parts, cfg.max_images_per_prompt, cfg.max_image_px)
        meta = {
            "mission_id": ctx.mission_id,
            "step": ctx.step,
            "anticipation": ctx.ablation.anticipation,
            "anticipation_hfov_deg": ctx.ablation.anticipation_hfov_deg,
            "spatial_map": ctx.ablation.spatial_map,
            "layout": layout,
            "prompt_config": cfg.describe(),
            "scene_graph": bool(self._scene_graph(ctx, cfg)),
        }
        return Prompt(system=SYSTEM_PROMPT, parts=parts, candidate_indices=indices, meta=meta)

    def _mosaic(self, tiles: list[Tile], cfg: PromptConfig) -> np.ndarray:
        px = cfg.image_px
        rows = max(len(t.images) for t in tiles)
        cols = best_columns(len(tiles), px, px * rows,
                            lambda w, h: image_tokens_by(cfg.image_token_rule, *_capped(w, h, cfg.max_image_px)))
        return cap_side(mosaic(tiles, px, cols), cfg.max_image_px)

    def _spatial_map(self, ctx: StepContext, cfg: PromptConfig) -> list[PromptPart]:
        if not (ctx.ablation.spatial_map and ctx.spatial_map_rgb is not None):
            return []
        return [
            "\nSpatial map (top-down view of the reconstructed building; the line is your trajectory, "
            "the arrow is you, numbers are the candidates): ",
            PromptImage("spatial_map", cap_side(np.asarray(ctx.spatial_map_rgb), cfg.max_image_px)),
            "\n",
        ]

    def _scene_graph(self, ctx: StepContext, cfg: PromptConfig | None = None) -> list[PromptPart]:
        """The scene graph block (issue 32): the whole map's rooms, objects and openings, and where the
        agent is; nothing when switched off or when the mission has no graph."""
        cfg = cfg or self.config
        if not cfg.scene_graph or ctx.scene_graph is None or not ctx.scene_graph.rooms:
            return []
        text = scene_graph_text(ctx.scene_graph, ctx.pose.position_m, cfg.scene_graph_max_chars)
        return [text + "\n\n"]

    def _history(self, history: list[HistoryItem], cfg: PromptConfig | None = None,
                 tiles: dict[str, list[Tile]] | None = None) -> list[PromptPart]:
        cfg = cfg or self.config
        if not history:
            return ["History: this is the first step; nothing has happened yet.\n"]
        items = history[-cfg.max_history_items :] if cfg.max_history_items else []
        parts: list[PromptPart] = ["History (observations joined by the actions taken, oldest first):\n"]
        if len(items) < len(history):
            parts.append(f"(... {len(history) - len(items)} earlier items omitted ...)\n")
        framed = len(items) if cfg.max_history_frames is None else min(len(items), cfg.max_history_frames)
        for k, item in enumerate(items):
            parts.append(f"[step {item.step + 1}] ")
            if k < len(items) - framed:
                parts.append("(image dropped)")
            elif tiles is not None:
                parts.append(f"(history tile {item.step + 1})")
                tiles["history"].append(Tile(str(item.step + 1), (item.image,)))
            else:
                img = item.image if max(item.image.shape[:2]) <= cfg.image_px else fit(item.image, cfg.image_px)
                parts.append(PromptImage(f"history_step{item.step + 1}", cap_side(img, cfg.max_image_px)))
            if item.action is not None:
                parts.append(f" -> {item.action.describe()} ->\n")
            else:
                parts.append("\n")
        return parts

    def _candidate(self, ctx: StepContext, view: CandidateView, cfg: PromptConfig | None = None,
                   tiles: dict[str, list[Tile]] | None = None) -> list[PromptPart]:
        cfg = cfg or self.config
        c = view.candidate
        parts: list[PromptPart] = [f"Candidate {c.index}: "]
        anticipated = (view.anticipated_rgb if c.kind != CandidateKind.STOP and ctx.ablation.anticipation
                       else None)
        if tiles is not None:
            if view.observed_rgb is not None or anticipated is not None:
                tiles["candidates"].append(Tile(str(c.index), (view.observed_rgb, anticipated)))
                parts.append(f"[views: cell {c.index} of the candidate views] ")
            if c.kind == CandidateKind.STOP:
                parts.append("[action: stop here - the instruction's destination is reached]\n")
            else:
                parts.append(f"[action: {describe_candidate(view)}]\n")
            return parts
        if c.kind == CandidateKind.STOP:
            if view.observed_rgb is not None:
                parts += ["[observed view] ", PromptImage(f"cand{c.index}_observed", self._img(view.observed_rgb, cfg)),
                          " "]
            parts.append("[action: stop here - the instruction's destination is reached]\n")
            return parts
        if view.observed_rgb is not None:
            parts += ["[observed view] ", PromptImage(f"cand{c.index}_observed", self._img(view.observed_rgb, cfg)), " "]
        parts.append(f"[action: {describe_candidate(view)}]")
        if anticipated is not None:
            parts.append(" -> if I took this action, I would partially imagine the next view: ")
            parts.append(PromptImage(f"cand{c.index}_anticipated", self._img(anticipated, cfg)))
        parts.append("\n")
        return parts


def _capped(w: int, h: int, max_px: int | None) -> tuple[int, int]:
    if max_px is None or max(w, h) <= max_px:
        return w, h
    s = max_px / max(w, h)
    return max(1, round(w * s)), max(1, round(h * s))


def _as_panel(parts: list[PromptPart], max_images: int, max_image_px: int | None) -> list[PromptPart]:
    """Over the image limit even as a mosaic: every composite moves into one stacked panel at the end,
    and each section names its place in it."""
    images = [p for p in parts if isinstance(p, PromptImage)]
    if len(images) <= max_images:
        return parts
    out: list[PromptPart] = []
    k = 0
    for p in parts:
        if isinstance(p, PromptImage):
            k += 1
            out.append(f"(panel section {k} of {len(images)}, counted from the top)")
        else:
            out.append(p)
    out.append(f"\nPanel ({len(images)} sections, top to bottom: "
               f"{', '.join(i.tag.replace('_', ' ') for i in images)}): ")
    out.append(PromptImage("panel", cap_side(stack([i.rgb for i in images]), max_image_px)))
    return out


# --- answers ------------------------------------------------------------------------------------------

_JSON_OBJECT = re.compile(r"\{.*\}", re.DOTALL)
_THINK = re.compile(r"<think>(.*?)</think>", re.DOTALL | re.IGNORECASE)


def split_thinking(text: str | None) -> tuple[str, str]:
    """(answer, thinking): a reasoning model's ``<think>...</think>`` blocks taken out of its answer.

    Servers with a reasoning parser drop the opening tag (the chat template opens it), leaving
    ``...</think>{json}``; an unterminated ``<think>`` (the reply cut at its token limit) is all thinking.
    """
    text = text or ""
    thinking = [m.strip() for m in _THINK.findall(text)]
    text = _THINK.sub("", text)
    low = text.lower()
    if "</think>" in low:
        k = low.rindex("</think>")
        thinking.append(text[:k].replace("<think>", "").strip())
        text = text[k + len("</think>"):]
    elif "<think>" in low:
        k = low.index("<think>")
        thinking.append(text[k + len("<think>"):].strip())
        text = text[:k]
    return text.strip(), "\n".join(t for t in thinking if t)


def _answer_object(text: str) -> dict:
    """The first JSON object with an "action" field, wherever it sits in prose (prose may hold braces
    of its own, so each ``{`` is tried as a start)."""
    decoder = json.JSONDecoder()
    first_error: str | None = None
    found_object = False
    for m in re.finditer(r"\{", text):
        try:
            obj, _ = decoder.raw_decode(text, m.start())
        except json.JSONDecodeError as exc:
            first_error = first_error or exc.msg
            continue
        if isinstance(obj, dict):
            found_object = True
            if "action" in obj:
                return obj
    if found_object:
        raise AnswerError('the JSON object has no "action" field')
    if first_error is not None and _JSON_OBJECT.search(text):
        raise AnswerError(f"the JSON object is malformed ({first_error})")
    raise AnswerError("the answer contains no JSON object")


def parse_answer(text: str | None, valid_indices: list[int]) -> tuple[int, str]:
    """Parse ``{"action": k, "reasoning": "..."}`` (code fences, surrounding prose and ``<think>``
    blocks tolerated).

    Returns (candidate index, reasoning); raises :class:`AnswerError` saying what is wrong, which the
    corrective re-ask quotes back to the model.
    """
    text, _ = split_thinking(text)
    if not text or not text.strip():
        raise AnswerError("the answer was empty")
    obj = _answer_object(text)
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
