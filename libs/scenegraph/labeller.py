"""Who names the rooms and objects of a scene graph (issue 32): a labeller backend, chosen by name.

- ``sim``: the map's semantic labels (a simulator's semantic camera, or a detector upstream) - what
  :func:`build_scene_graph` reads today.
- ``none``: the geometric graph: the labels are ignored, rooms come from the mapper's regions, unnamed.
- ``mllm``: the geometric graph, then the configured OpenAI-compatible chat model is asked once per region,
  with a few of that region's tour frames (recorded RGB), what room this is and which objects it holds.
  The answers are cached (a JSON file the caller keeps beside the map version: same frames, same model,
  no second call) and counted (calls, tokens, dollars from :mod:`shared.pricing`) in a
  :class:`~shared.schemas.UsageData` for the cost ledger.

Objects the model names have no measured position: they are added to their room at its centroid with
``points=0`` and size 0, which says "named by the labeller, not seen in the cloud". A real robot needs
this (it has no semantic camera); the positions of such objects would need a detector.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field, field_validator

from shared.cloud import PointCloud
from shared.pricing import PriceTable
from shared.registry import BackendConfig, Registry
from shared.schemas import NavGraph, SceneGraph, SceneObject, UsageData

from .builder import SceneGraphConfig, build_scene_graph

# The labelling prompt. The stand-in (services/planner/tools/llm_standin.py) recognises it by its first
# words and answers deterministically from the pixels; keep them if you reword the rest.
LABEL_SYSTEM = (
    "You label rooms of a building for a robot's map. You see a few photos taken inside ONE room. "
    "Say what kind of room it is (one or two lowercase words, e.g. kitchen, bedroom, bathroom, living room, "
    "hallway, office, dining room) and list the objects you see in it (lowercase nouns, at most 12). "
    'Answer with exactly one JSON object and nothing else: {"room": "<room type>", "objects": ["<noun>", ...]}'
)
_WORD = re.compile(r"^[a-z][a-z ]{0,40}$")


class LabellerError(RuntimeError):
    """The labeller could not label (no endpoint, a refused answer after its retry). ``usage``: what the
    calls made before the failure cost (they are billed all the same)."""

    def __init__(self, message: str, usage: UsageData | None = None):
        super().__init__(message)
        self.usage = usage or UsageData()


@dataclass
class LabelledGraph:
    graph: SceneGraph
    usage: UsageData = field(default_factory=UsageData)
    answers: dict[int, dict] = field(default_factory=dict)  # region -> {"room": ..., "objects": [...]}


class Labeller:
    name = "labeller"

    def label(self, cloud: PointCloud, navigation: NavGraph | None = None,
              frames: Mapping[int, Sequence[np.ndarray]] | None = None, *, map_id: str = "", version: int = 0,
              cache_path: str | Path | None = None) -> LabelledGraph:
        raise NotImplementedError


LABELLERS: Registry[Labeller] = Registry("scene-graph labeller")


def _unlabelled(cloud: PointCloud) -> PointCloud:
    return PointCloud(cloud.xyz, cloud.rgb, None, {})


def geometric_graph(cloud: PointCloud, navigation: NavGraph | None = None, *, map_id: str = "",
                    version: int = 0) -> SceneGraph:
    """The graph without names: rooms from the mapper's regions, their connections (what a map keeps
    when its labeller fails)."""
    return build_scene_graph(_unlabelled(cloud), navigation, map_id=map_id, version=version)


@LABELLERS.register("sim", BackendConfig)
class SimLabeller(Labeller):
    """The map's own semantic labels."""

    name = "sim"

    def __init__(self, config: BackendConfig):
        self.config = config

    def label(self, cloud, navigation=None, frames=None, *, map_id="", version=0, cache_path=None) -> LabelledGraph:
        return LabelledGraph(build_scene_graph(cloud, navigation, map_id=map_id, version=version))


@LABELLERS.register("none", BackendConfig)
class NoLabeller(Labeller):
    """The geometric graph: rooms from the mapper's regions, unnamed."""

    name = "none"

    def __init__(self, config: BackendConfig):
        self.config = config

    def label(self, cloud, navigation=None, frames=None, *, map_id="", version=0, cache_path=None) -> LabelledGraph:
        return LabelledGraph(build_scene_graph(_unlabelled(cloud), navigation, map_id=map_id, version=version))


class MllmLabellerConfig(BackendConfig):
    """An OpenAI-compatible endpoint; the key from ``api_key`` or the ``api_key_env`` variable."""

    model: str = "gpt-5.1"
    base_url: str = "https://api.openai.com/v1"
    api_key: str | None = Field(default=None, repr=False)
    api_key_env: str = "OPENAI_API_KEY"
    timeout_s: float = Field(60.0, gt=0.0, le=600.0)
    frames_per_region: int = Field(3, ge=1, le=8)
    image_px: int = Field(384, ge=64, le=1024)  # frames are resized so that their longer side is this
    max_regions: int = Field(200, ge=1, le=10_000)  # a budget: a map with more regions is refused, not billed
    max_completion_tokens: int = Field(300, ge=16, le=4096)

    @field_validator("base_url")
    @classmethod
    def _url(cls, v: str) -> str:
        if not v.startswith(("http://", "https://")):
            raise ValueError(f"base_url must be http(s), got {v!r}")
        return v.rstrip("/")


def _data_url(rgb: np.ndarray, px: int) -> str:
    rgb = np.ascontiguousarray(rgb, np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise LabellerError(f"a frame must be (H, W, 3) RGB, got {rgb.shape}")
    scale = px / max(rgb.shape[:2])
    if scale < 1.0:
        rgb = cv2.resize(rgb, (max(1, round(rgb.shape[1] * scale)), max(1, round(rgb.shape[0] * scale))),
                         interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
    if not ok:
        raise LabellerError("frame encoding failed")
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode()


def parse_label_answer(text: str) -> dict:
    """``{"room": str, "objects": [str]}`` from the model's answer (code fences and prose tolerated);
    raises :class:`LabellerError` saying what is wrong. Words are lower-cased and checked: an answer is
    written into a map others navigate by."""
    m = re.search(r"\{.*\}", text or "", re.DOTALL)
    if not m:
        raise LabellerError("the answer contains no JSON object")
    try:
        obj = json.loads(m.group(0))
    except json.JSONDecodeError as exc:
        raise LabellerError(f"the JSON object is malformed ({exc.msg})") from None
    room = str(obj.get("room", "")).strip().lower() if isinstance(obj, dict) else ""
    if not _WORD.match(room):
        raise LabellerError(f'"room" must be one or two lowercase words, got {obj.get("room") if isinstance(obj, dict) else obj!r}')
    objects = obj.get("objects", [])
    if not isinstance(objects, list):
        raise LabellerError('"objects" must be a list of nouns')
    clean = [str(o).strip().lower() for o in objects[:12]]
    return {"room": room, "objects": [o for o in clean if _WORD.match(o)]}


@LABELLERS.register("mllm", MllmLabellerConfig)
class MllmLabeller(Labeller):
    """Names each region of the geometric graph by asking a multimodal chat model (see the module)."""

    name = "mllm"

    def __init__(self, config: MllmLabellerConfig):
        self.config = config
        self._lock = threading.Lock()

    def _key(self) -> str:
        key = self.config.api_key or os.environ.get(self.config.api_key_env)
        if not key:
            if "api.openai.com" in self.config.base_url:
                raise LabellerError(f"no API key: set {self.config.api_key_env} or api_key")
            key = "not-needed"  # local servers usually take any key
        return key

    def _ask(self, client, images: list[str], usage: UsageData) -> dict:
        cfg = self.config
        content = [{"type": "text", "text": f"{len(images)} photos of one room:"}]
        content += [{"type": "image_url", "image_url": {"url": u, "detail": "low"}} for u in images]
        messages = [{"role": "system", "content": LABEL_SYSTEM}, {"role": "user", "content": content}]
        price = PriceTable().price(cfg.model)
        error: LabellerError | None = None
        for attempt in range(2):  # the answer, then one corrective re-ask
            r = client.post(f"{cfg.base_url}/chat/completions",
                            json={"model": cfg.model, "messages": messages,
                                  "max_completion_tokens": cfg.max_completion_tokens})
            if r.status_code != 200:
                raise LabellerError(f"{cfg.model}: HTTP {r.status_code}: {r.text[:200]}")
            body = r.json()
            u = body.get("usage") or {}
            n_in, n_out = int(u.get("prompt_tokens") or 0), int(u.get("completion_tokens") or 0)
            usage.calls += 1
            usage.prompt_tokens += n_in
            usage.completion_tokens += n_out
            usage.cost_usd += (n_in * price.input_per_1m_usd + n_out * price.output_per_1m_usd) / 1e6
            text = ((body.get("choices") or [{}])[0].get("message") or {}).get("content") or ""
            try:
                return parse_label_answer(text)
            except LabellerError as exc:
                error = exc
                if attempt == 0:
                    usage.reasks += 1
                    messages = messages + [{"role": "assistant", "content": text},
                                           {"role": "user", "content": f"Your answer was invalid: {exc}. "
                                                                       "Reply with exactly one JSON object."}]
        raise LabellerError(f"{cfg.model}: {error}")

    def label(self, cloud, navigation=None, frames=None, *, map_id="", version=0, cache_path=None) -> LabelledGraph:
        import httpx

        cfg = self.config
        graph = build_scene_graph(_unlabelled(cloud), navigation, map_id=map_id, version=version)
        frames = frames or {}
        regions = sorted({r.region for r in graph.rooms if r.region is not None and r.region in frames})
        if len(regions) > cfg.max_regions:
            raise LabellerError(f"{len(regions)} regions to label, the budget is {cfg.max_regions}")
        cache_file = Path(cache_path) if cache_path else None
        cache: dict[str, dict] = {}
        if cache_file is not None and cache_file.is_file():
            try:
                cache = json.loads(cache_file.read_text())
            except (OSError, ValueError):
                cache = {}  # a torn cache costs calls, never a wrong label
        usage, answers, asked = UsageData(), {}, False
        try:
            with httpx.Client(timeout=cfg.timeout_s, headers={"Authorization": f"Bearer {self._key()}"}) as client:
                for region in regions:
                    picked = _spread(list(frames[region]), cfg.frames_per_region)
                    images = [_data_url(f, cfg.image_px) for f in picked]
                    digest = hashlib.sha256("".join([cfg.model, LABEL_SYSTEM, *images]).encode()).hexdigest()
                    key = f"{region}:{digest}"
                    if key in cache:
                        usage.cache_hits += 1
                        answers[region] = cache[key]
                        continue
                    asked = True
                    answers[region] = cache[key] = self._ask(client, images, usage)
        except LabellerError as exc:
            raise LabellerError(str(exc), usage) from None
        except (httpx.HTTPError, ValueError) as exc:  # unreachable, timed out, a body that is no JSON
            raise LabellerError(f"{cfg.model}: {type(exc).__name__}: {exc}", usage) from None
        finally:
            # The answers paid for are kept even when a later region fails: a retry asks only the rest.
            if cache_file is not None and asked:
                cache_file.parent.mkdir(parents=True, exist_ok=True)
                tmp = cache_file.with_suffix(cache_file.suffix + ".part")
                tmp.write_text(json.dumps(cache, indent=1, sort_keys=True))
                tmp.replace(cache_file)
        return LabelledGraph(apply_answers(graph, answers), usage, answers)


def _spread(items: list, k: int) -> list:
    """``k`` items spread evenly over the list (a tour's frames: not three of the same corner)."""
    if len(items) <= k:
        return items
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, k).round()]


def apply_answers(graph: SceneGraph, answers: Mapping[int, dict]) -> SceneGraph:
    """The graph with each answered region's rooms named and the objects the model listed added at the
    room's centroid (``points=0``: named, not measured)."""
    rooms, objects = [], list(graph.objects)
    for r in graph.rooms:
        a = answers.get(r.region) if r.region is not None else None
        if a is None:
            rooms.append(r)
            continue
        rooms.append(r.model_copy(update={"room_type": a["room"]}))
        for k, label in enumerate(a.get("objects", [])):
            objects.append(SceneObject(object_id=f"{r.room_id}-named-{k}", label=label, position_m=r.centroid_m,
                                       size_m=(0.0, 0.0, 0.0), room_id=r.room_id, points=0))
    named = any(r.room_type for r in rooms)
    return graph.model_copy(update={"rooms": rooms, "objects": objects, "labelled": graph.labelled or named})
