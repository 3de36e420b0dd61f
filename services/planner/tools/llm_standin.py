"""An OpenAI-compatible chat-completions stand-in for benchmarks and tests (never for real results).

A real HTTP server (stdlib ``ThreadingHTTPServer`` on 127.0.0.1) speaking ``POST /v1/chat/completions``
with the latency, token counts, answers and failures of a hosted MLLM, so that evaluation runs, the
planner's retries and fleet benchmarks are exercised end to end without an API key or a bill:

    .venv/bin/python -m services.planner.tools.llm_standin --port 8088 --latency-s 2 \
        --latency-dist lognormal --policy heuristic --error-rate-429 0.05 --error-rate-500 0.02

- **Latency**: ``fixed``, ``uniform`` (latency * [1 - spread, 1 + spread]) or ``lognormal`` (median
  latency, sigma = spread); draws come from a seeded generator.
- **Tokens** come from the real request, counted by :mod:`services.planner.core.tokens` (a documented
  deterministic approximation: tiktoken needs a BPE download; images by OpenAI's exact tile rule).
- **Answers** come from a named deterministic policy (:data:`STANDIN_POLICIES`). ``heuristic`` rebuilds a
  planner :class:`StepContext` from the prompt text alone (instruction, step, each candidate's action
  text, the history's actions, dead-reckoned into poses) and asks the planner's own heuristic policy, so
  a run with the stand-in navigates by the instruction's turns and distances (the prompt carries images,
  not labels). ``straight`` takes the candidate nearest straight ahead and stops after ``--stop-after``
  steps. There is no ``oracle``: a prompt carries no ground truth (goal, geodesic), by design; use the
  planner's ``oracle`` policy directly for an upper bound.
- **Emulation** (``--emulate vllm|ollama|openai``): the server's limits and refusals, with its error
  bodies, so the planner's profiles are tested against what real servers do (see :data:`EMULATIONS`):
  vLLM refuses more images than ``--limit-mm-per-prompt`` (default 1: "At most 1 image(s) may be provided
  in one request.", vllm#13513) and prompts over ``--max-model-len``, as ``{"object": "error", ...}``;
  OpenAI refuses ``max_tokens`` and a non-default ``temperature`` on reasoning models, unknown fields and
  over-long prompts (``context_length_exceeded``), as ``{"error": {...}}``; Ollama ignores fields it does
  not know and silently cuts an over-long prompt to its ``num_ctx`` from the start (the model then never
  sees the instruction: here, an answer without JSON). Images are counted by each server's rule.
- **Failures**: 429 with ``Retry-After``, 500, and timeouts (the reply is held ``--timeout-sleep-s``,
  longer than the client waits), each drawn per request at its rate, or scripted in order
  (``--fault-script 429,500,timeout``) for tests.

The stand-in is a planner tool (it imports the planner core to reuse the heuristic's logic); no service
depends on it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import random
import re
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.planner.core.context import CandidateView, StepContext
from services.planner.core.heuristic import HeuristicConfig, HeuristicPolicy
from services.planner.core.tokens import message_tokens, text_tokens
from shared.schemas import Candidate, CandidateKind, Pose

log = logging.getLogger(__name__)

Fault = Literal["429", "500", "timeout", "ok"]


class StandinConfig(BaseModel):
    """How the stand-in behaves; every rate is a probability per request."""

    model_config = ConfigDict(extra="forbid")

    latency_s: float = Field(2.0, ge=0.0, le=600.0)
    latency_dist: Literal["fixed", "uniform", "lognormal"] = "fixed"
    latency_spread: float = Field(0.3, ge=0.0, le=3.0)  # uniform: +-fraction; lognormal: sigma
    policy: str = "heuristic"
    stop_after: int = Field(6, ge=1, le=1000)  # the ``straight`` policy stops at this step
    error_rate_429: float = Field(0.0, ge=0.0, le=1.0)
    error_rate_500: float = Field(0.0, ge=0.0, le=1.0)
    timeout_rate: float = Field(0.0, ge=0.0, le=1.0)
    retry_after_s: float = Field(1.0, ge=0.0, le=3600.0)
    timeout_sleep_s: float = Field(120.0, ge=0.0, le=3600.0)
    fault_script: list[Fault] = Field(default_factory=list)  # the first requests' outcomes, in order
    seed: int = 0
    max_body_bytes: int = Field(64 * 1024 * 1024, ge=1024)
    emulate: Literal["none", "vllm", "ollama", "openai"] = "none"
    emulate_max_images: int | None = Field(None, ge=1, le=10_000)  # None: the emulated server's default
    emulate_context_tokens: int | None = Field(None, ge=256, le=10_000_000)  # None: its default


@dataclass(frozen=True)
class Emulation:
    """What one server enforces (its documented defaults) and how it words a refusal."""

    max_images: int | None
    context_tokens: int
    image_rule: str
    error_style: Literal["vllm", "openai"]
    params: frozenset[str] | None  # accepted body fields; None: unknown fields are ignored
    rejected_params: dict[str, str] = field(default_factory=dict)  # field -> the server's message
    truncates: bool = False  # over-long prompts are cut, not refused (Ollama)


_CHAT_FIELDS = frozenset({
    "model", "messages", "temperature", "top_p", "n", "stream", "stop", "presence_penalty", "frequency_penalty",
    "logit_bias", "logprobs", "top_logprobs", "user", "seed", "response_format", "tools", "tool_choice",
    "max_tokens", "max_completion_tokens", "reasoning_effort", "stream_options", "parallel_tool_calls",
    "metadata", "store", "service_tier", "modalities", "prediction", "audio", "verbosity", "web_search_options",
})

EMULATIONS: dict[str, Emulation] = {
    # vLLM serving Qwen2.5-VL: one image unless --limit-mm-per-prompt says more, --max-model-len 32768;
    # unknown fields are logged and ignored.
    "vllm": Emulation(max_images=1, context_tokens=32_768, image_rule="qwen_patches", error_style="vllm",
                      params=None),
    # Ollama's OpenAI compatibility: num_ctx 4096, unknown fields ignored, the prompt's start cut off.
    "ollama": Emulation(max_images=None, context_tokens=4096, image_rule="qwen_patches", error_style="openai",
                        params=None, truncates=True),
    # OpenAI with a reasoning model (gpt-5.1): 500 images, a 400k window, max_tokens refused.
    "openai": Emulation(max_images=500, context_tokens=400_000, image_rule="openai_tiles", error_style="openai",
                        params=_CHAT_FIELDS, rejected_params={
                            "max_tokens": "Unsupported parameter: 'max_tokens' is not supported with this model. "
                                          "Use 'max_completion_tokens' instead.",
                        }),
}


class EmulatedRefusal(Exception):
    """A request the emulated server refuses: (status, message, param, code)."""

    def __init__(self, status: int, message: str, param: str | None = None, code: str | None = None):
        super().__init__(message)
        self.status, self.message, self.param, self.code = status, message, param, code


# --- the prompt, read back ----------------------------------------------------------------------------

_INSTRUCTION = re.compile(r"Instruction: (.*?)\n\n", re.S)
_STEP = re.compile(r"Step (\d+) of at most (\d+)\. Candidate sub-paths:")
_CANDIDATE = re.compile(r"Candidate (\d+): [^\n]*?\[action: ([^\]]*)\]")
# A history item's image is inline (<image>), a mosaic tile or dropped by the budget ("(...)").
_HISTORY_ACTION = re.compile(r"\[step (\d+)\] (?:<image>|\([^)\n]*\)) -> (.*?) ->")
_NUM = r"(\d+(?:\.\d+)?)"
_TURN = re.compile(rf"turn (left|right) (\d+) degrees and move (?:forward )?{_NUM} m")
_AROUND = re.compile(rf"turn around and move (?:forward )?{_NUM} m")
_STRAIGHT = re.compile(rf"(?:go straight|move forward) {_NUM} m")
_BACK = re.compile(rf"go back to the previous position \({_NUM} m")


class PromptReadError(ValueError):
    """The request does not look like the planner's sub-path prompt."""


@dataclass(frozen=True)
class Move:
    """One action read from prompt text: agent-relative turn and distance, or backtrack / stop."""

    kind: CandidateKind
    angle_rad: float = 0.0
    distance_m: float = 0.0


def read_action(text: str) -> Move:
    """The action a candidate or history item describes (the inverse of ``describe_candidate`` and
    ``ActionRecord.describe``; angles are in whole degrees there, so this is exact to 0.5 deg)."""
    text = text.strip()
    if text.startswith("stop"):
        return Move(CandidateKind.STOP)
    if m := _BACK.search(text):
        return Move(CandidateKind.BACKTRACK, 0.0, float(m.group(1)))
    if m := _TURN.search(text):
        sign = 1.0 if m.group(1) == "left" else -1.0
        return Move(CandidateKind.WAYPOINT, sign * math.radians(float(m.group(2))), float(m.group(3)))
    if m := _AROUND.search(text):
        return Move(CandidateKind.WAYPOINT, math.pi, float(m.group(1)))
    if m := _STRAIGHT.search(text):
        return Move(CandidateKind.WAYPOINT, 0.0, float(m.group(1)))
    raise PromptReadError(f"unreadable action {text!r}")


@dataclass
class ReadPrompt:
    """What the stand-in understood of one request."""

    instruction: str
    step: int  # 0-based, as in the planner
    max_steps: int
    candidates: list[tuple[int, Move]]
    history: list[Move]

    @property
    def indices(self) -> list[int]:
        return [i for i, _ in self.candidates]


def user_text(messages: list[dict]) -> str:
    """The first user message's text parts joined, each image as ``<image>`` (a re-ask's later messages
    are ignored: the step is the same)."""
    for m in messages:
        if m.get("role") != "user":
            continue
        content = m.get("content")
        if isinstance(content, str):
            return content
        return "".join(p.get("text", "") if p.get("type") == "text" else "<image>" for p in content or [])
    raise PromptReadError("no user message")


def read_prompt(messages: list[dict]) -> ReadPrompt:
    text = user_text(messages)
    mi, ms = _INSTRUCTION.search(text), _STEP.search(text)
    if mi is None or ms is None:
        raise PromptReadError("not the planner's prompt (no instruction or step line)")
    body = text[ms.end():]
    candidates = [(int(m.group(1)), read_action(m.group(2))) for m in _CANDIDATE.finditer(body)]
    if not candidates:
        raise PromptReadError("the prompt lists no candidates")
    history = [read_action(m.group(2)) for m in _HISTORY_ACTION.finditer(text[:ms.start()])]
    return ReadPrompt(mi.group(1).strip(), int(ms.group(1)) - 1, int(ms.group(2)), candidates, history)


def dead_reckon(history: list[Move]) -> tuple[np.ndarray, float, list[np.ndarray]]:
    """Positions along the history's actions from the origin (heading 0), assuming the agent faces the
    way it moved. Returns (trajectory (N, 3), heading, the backtrack stack of earlier nodes)."""
    pos, heading = np.zeros(3), 0.0
    traj, visited = [pos.copy()], []
    for mv in history:
        if mv.kind == CandidateKind.BACKTRACK:
            target = visited.pop() if visited else pos
            d = target - pos
            if np.hypot(d[0], d[1]) > 1e-6:
                heading = math.atan2(d[1], d[0])
            pos = target.copy()
        elif mv.kind == CandidateKind.WAYPOINT:
            visited.append(pos.copy())
            heading += mv.angle_rad
            pos = pos + mv.distance_m * np.array([math.cos(heading), math.sin(heading), 0.0])
        traj.append(pos.copy())
    return np.asarray(traj), heading, visited


def step_context(p: ReadPrompt) -> StepContext:
    """A planner step context from the prompt alone (no images, labels or panorama)."""
    traj, heading, visited = dead_reckon(p.history)
    pose = Pose(position_m=tuple(traj[-1].tolist()), heading_rad=heading)
    views = []
    for index, mv in p.candidates:
        if mv.kind == CandidateKind.BACKTRACK and visited:
            dx, dy = (visited[-1] - traj[-1])[:2]
            angle = math.remainder(math.atan2(dy, dx) - heading, 2 * math.pi)
            c = Candidate(index=index, kind=mv.kind, dx_m=float(dx), dy_m=float(dy), angle_rad=angle,
                          distance_m=mv.distance_m)
        else:
            world = heading + mv.angle_rad
            c = Candidate(index=index, kind=mv.kind, dx_m=mv.distance_m * math.cos(world),
                          dy_m=mv.distance_m * math.sin(world), angle_rad=mv.angle_rad, distance_m=mv.distance_m)
        views.append(CandidateView(candidate=c))
    return StepContext(instruction=p.instruction, step=p.step, pose=pose, candidates=views, trajectory_m=traj,
                       max_steps=p.max_steps)


# --- policies -----------------------------------------------------------------------------------------

class StandinPolicy:
    """Answers one conversation's steps in order (one instance per instruction)."""

    def answer(self, p: ReadPrompt) -> tuple[int, str]:
        raise NotImplementedError


class HeuristicStandin(StandinPolicy):
    """The planner's heuristic policy on the context read back from the prompt."""

    def __init__(self, cfg: StandinConfig):
        self._policy = HeuristicPolicy(HeuristicConfig())
        self._policy.reset("standin")

    def answer(self, p: ReadPrompt) -> tuple[int, str]:
        d = self._policy.decide(step_context(p))
        return d.candidate_index, d.reasoning


class StraightStandin(StandinPolicy):
    """The candidate nearest straight ahead (longest on ties); stop at step ``stop_after``."""

    def __init__(self, cfg: StandinConfig):
        self.stop_after = cfg.stop_after

    def answer(self, p: ReadPrompt) -> tuple[int, str]:
        stop = next((i for i, mv in p.candidates if mv.kind == CandidateKind.STOP), None)
        moves = [(abs(mv.angle_rad), -mv.distance_m, i) for i, mv in p.candidates if mv.kind == CandidateKind.WAYPOINT]
        if stop is not None and (p.step + 1 >= self.stop_after or not moves):
            return stop, f"step {p.step + 1}: stop"
        if not moves:
            return p.candidates[0][0], "no waypoint"
        return min(moves)[2], "nearest straight ahead"


STANDIN_POLICIES: dict[str, Callable[[StandinConfig], StandinPolicy]] = {
    "heuristic": HeuristicStandin,
    "straight": StraightStandin,
}


# --- the server ---------------------------------------------------------------------------------------

@dataclass
class _Conversation:
    policy: StandinPolicy
    answers: dict[int, tuple[int, str]] = field(default_factory=dict)  # step -> answer (retries repeat it)
    lock: threading.Lock = field(default_factory=threading.Lock)


@dataclass
class StandinStats:
    requests: int = 0
    by_outcome: dict[str, int] = field(default_factory=dict)
    refusals: list[str] = field(default_factory=list)  # the emulated servers' refusal messages, in order
    images_per_request: list[int] = field(default_factory=list)
    prompt_tokens: int = 0
    completion_tokens: int = 0


class StandinServer:
    """The stand-in as a context manager: ``with StandinServer(cfg) as s: OpenAIConfig(base_url=s.url)``."""

    def __init__(self, config: StandinConfig | None = None, host: str = "127.0.0.1", port: int = 0):
        self.config = config or StandinConfig()
        if self.config.policy not in STANDIN_POLICIES:
            raise ValueError(f"unknown stand-in policy {self.config.policy!r}; have {sorted(STANDIN_POLICIES)}")
        self.stats = StandinStats()
        self._rng = random.Random(self.config.seed)
        self._script = list(self.config.fault_script)
        self._lock = threading.Lock()
        self._conversations: dict[tuple[str, int], _Conversation] = {}
        # The last user texts received (images as <image>), bounded: tests read what a client really sent.
        self.prompts: deque[str] = deque(maxlen=64)
        self.httpd = ThreadingHTTPServer((host, port), _handler(self))
        self.httpd.daemon_threads = True
        self.url = f"http://{host}:{self.httpd.server_address[1]}/v1"
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05},
                                        daemon=True)

    def __enter__(self) -> StandinServer:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(timeout=5)

    def draw(self) -> tuple[Fault, float]:
        """This request's outcome and latency (under the lock: one seeded sequence for all threads)."""
        cfg = self.config
        with self._lock:
            self.stats.requests += 1
            if self._script:
                fault = self._script.pop(0)
            else:
                u = self._rng.random()
                fault = "ok"
                for name, rate in (("429", cfg.error_rate_429), ("500", cfg.error_rate_500),
                                   ("timeout", cfg.timeout_rate)):
                    if u < rate:
                        fault = name
                        break
                    u -= rate
            if cfg.latency_dist == "fixed":
                latency = cfg.latency_s
            elif cfg.latency_dist == "uniform":
                latency = cfg.latency_s * self._rng.uniform(1 - cfg.latency_spread, 1 + cfg.latency_spread)
            else:
                latency = cfg.latency_s * math.exp(self._rng.gauss(0.0, cfg.latency_spread))
            self.stats.by_outcome[fault] = self.stats.by_outcome.get(fault, 0) + 1
        return fault, max(0.0, latency)

    def answer(self, messages: list[dict]) -> str:
        with self._lock:
            self.prompts.append(user_text(messages))
        if is_label_prompt(messages):
            return label_answer(messages)
        p = read_prompt(messages)
        key = (p.instruction, p.max_steps)
        with self._lock:
            conv = self._conversations.get(key)
            if conv is None or p.step == 0 and 0 in conv.answers or p.step < max(conv.answers, default=-1):
                # A new episode (or the same instruction again from its start): a fresh policy.
                conv = self._conversations[key] = _Conversation(STANDIN_POLICIES[self.config.policy](self.config))
        with conv.lock:
            if p.step not in conv.answers:
                conv.answers[p.step] = conv.policy.answer(p)
            index, reasoning = conv.answers[p.step]
        return json.dumps({"action": index, "reasoning": reasoning})

    @property
    def emulation(self) -> Emulation | None:
        return EMULATIONS.get(self.config.emulate)

    def image_rule(self) -> str:
        em = self.emulation
        return em.image_rule if em is not None else "openai_tiles"

    def check(self, body: dict, messages: list[dict], n_in: int) -> bool:
        """Raise :class:`EmulatedRefusal` where the emulated server would refuse ``body``; True when it
        would truncate the prompt instead (Ollama)."""
        em, cfg = self.emulation, self.config
        if em is None:
            return False
        for name, message in em.rejected_params.items():
            if name in body:
                raise EmulatedRefusal(400, message, name, "unsupported_parameter")
        if em.params is not None:
            unknown = sorted(set(body) - em.params)
            if unknown:
                raise EmulatedRefusal(400, f"Unrecognized request argument supplied: {unknown[0]}", unknown[0])
        if cfg.emulate == "openai" and "temperature" in body and body["temperature"] != 1:
            raise EmulatedRefusal(400, f"Unsupported value: 'temperature' does not support {body['temperature']} "
                                       "with this model. Only the default (1) value is supported.",
                                  "temperature", "unsupported_value")
        images = sum(1 for m in messages if isinstance(m.get("content"), list)
                     for p in m["content"] if isinstance(p, dict) and p.get("type") == "image_url")
        limit = cfg.emulate_max_images if cfg.emulate_max_images is not None else em.max_images
        if limit is not None and images > limit:
            if em.error_style == "vllm":
                raise EmulatedRefusal(400, f"At most {limit} image(s) may be provided in one request.")
            raise EmulatedRefusal(400, f"Invalid 'messages': {images} images, the maximum is {limit}.",
                                  "messages", "invalid_value")
        window = cfg.emulate_context_tokens or em.context_tokens
        completion = body.get("max_completion_tokens", body.get("max_tokens")) or 0
        if n_in + (completion if isinstance(completion, int) else 0) > window:
            if em.truncates:
                return True
            if em.error_style == "vllm":
                raise EmulatedRefusal(400, f"This model's maximum context length is {window} tokens. However, you "
                                           f"requested {n_in + completion} tokens ({n_in} in the messages, "
                                           f"{completion} in the completion). Please reduce the length of the "
                                           "messages or completion.")
            raise EmulatedRefusal(400, f"This model's maximum context length is {window} tokens. However, your "
                                       f"messages resulted in {n_in} tokens. Please reduce the length of the "
                                       "messages.", "messages", "context_length_exceeded")
        return False

    def count(self, n_in: int, n_out: int) -> None:
        with self._lock:
            self.stats.prompt_tokens += n_in
            self.stats.completion_tokens += n_out


# --- the scene-graph labeller's prompt (libs/scenegraph/labeller.py, issue 32) ----------------------------
# A deterministic answer from the pixels: the dominant channel of the frames' mean colour picks a room and
# its objects. Enough to test the labeller's mechanics (one call per region, frames sent, answers cached
# and counted); nothing here recognises a real room.
LABEL_PROMPT_START = "You label rooms"
LABEL_TABLE = {"red": ("kitchen", ["fridge", "stove"]), "green": ("bedroom", ["bed", "wardrobe"]),
               "blue": ("bathroom", ["toilet", "sink"]), "grey": ("hallway", [])}


def is_label_prompt(messages: list[dict]) -> bool:
    return any(m.get("role") == "system" and str(m.get("content", "")).startswith(LABEL_PROMPT_START)
               for m in messages)


def label_answer(messages: list[dict]) -> str:
    import base64

    import cv2

    means = []
    for m in messages:
        if m.get("role") != "user" or not isinstance(m.get("content"), list):
            continue
        for part in m["content"]:
            url = (part.get("image_url") or {}).get("url", "") if part.get("type") == "image_url" else ""
            if "," in url:
                img = cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
                if img is not None:
                    means.append(img.reshape(-1, 3)[:, ::-1].mean(axis=0))  # BGR -> RGB
    if not means:
        raise PromptReadError("a labelling prompt without images")
    mean = np.mean(means, axis=0)
    colour = "grey" if mean.max() - mean.min() < 30 else ("red", "green", "blue")[int(np.argmax(mean))]
    room, objects = LABEL_TABLE[colour]
    return json.dumps({"room": room, "objects": objects})


def _handler(server: StandinServer) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, fmt, *args):
            log.debug("%s " + fmt, self.address_string(), *args)

        def _send(self, status: int, obj: dict, headers: dict[str, str] | None = None) -> None:
            data = json.dumps(obj).encode()
            try:
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                for k, v in (headers or {}).items():
                    self.send_header(k, v)
                self.end_headers()
                self.wfile.write(data)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the client gave up (its timeout): nothing to tell it

        def _error(self, status: int, message: str, kind: str, headers=None) -> None:
            self._send(status, {"error": {"message": message, "type": kind, "code": status}}, headers)

        def _refuse(self, exc: EmulatedRefusal) -> None:
            if server.config.emulate == "vllm":
                self._send(exc.status, {"object": "error", "message": exc.message, "type": "BadRequestError",
                                        "param": exc.param, "code": exc.status})
            else:
                self._send(exc.status, {"error": {"message": exc.message, "type": "invalid_request_error",
                                                  "param": exc.param, "code": exc.code}})

        def do_GET(self):  # noqa: N802 - http.server naming
            if self.path.rstrip("/") in ("/v1/models", "/models"):
                entry = {"id": "standin", "object": "model"}
                if server.config.emulate == "vllm":  # vLLM reports its --max-model-len here
                    entry["max_model_len"] = server.config.emulate_context_tokens or EMULATIONS["vllm"].context_tokens
                self._send(200, {"object": "list", "data": [entry]})
            elif self.path == "/health":
                self._send(200, {"ok": True, "requests": server.stats.requests})
            else:
                self._error(404, f"no route {self.path}", "not_found")

        def do_POST(self):  # noqa: N802
            if self.path.rstrip("/") not in ("/v1/chat/completions", "/chat/completions"):
                self._error(404, f"no route {self.path}", "not_found")
                return
            try:
                n = int(self.headers.get("Content-Length", "0"))
            except ValueError:
                n = -1
            if not 0 < n <= server.config.max_body_bytes:
                self._error(413 if n > 0 else 400, "missing or oversized body", "invalid_request_error")
                return
            try:
                body = json.loads(self.rfile.read(n))
                messages = body["messages"]
                model = str(body.get("model", "standin"))
                if not isinstance(messages, list) or not messages:
                    raise ValueError("messages must be a non-empty list")
                n_in = message_tokens(messages, server.image_rule())
            except (ValueError, KeyError, TypeError) as exc:
                self._error(400, f"bad request: {exc}", "invalid_request_error")
                return
            try:
                truncated = server.check(body, messages, n_in)
            except EmulatedRefusal as exc:
                with server._lock:
                    server.stats.requests += 1
                    server.stats.by_outcome["refused"] = server.stats.by_outcome.get("refused", 0) + 1
                    server.stats.refusals.append(exc.message)
                self._refuse(exc)
                return
            with server._lock:
                server.stats.images_per_request.append(sum(
                    1 for m in messages if isinstance(m.get("content"), list)
                    for p in m["content"] if isinstance(p, dict) and p.get("type") == "image_url"))
            fault, latency = server.draw()
            if fault == "timeout":
                time.sleep(server.config.timeout_sleep_s)
                self._error(504, "held past the client's timeout", "timeout")
                return
            time.sleep(latency)
            if fault == "429":
                self._error(429, "rate limited (injected)", "rate_limit_exceeded",
                            {"Retry-After": f"{server.config.retry_after_s:g}"})
                return
            if fault == "500":
                self._error(500, "server error (injected)", "server_error")
                return
            if truncated:
                # Ollama keeps the prompt's end: the instruction is gone, and the model says so in prose.
                window = server.config.emulate_context_tokens or server.emulation.context_tokens
                self._complete(model, "I cannot see an instruction to follow, so I am not sure where to go.", window)
                return
            try:
                content = server.answer(messages)
            except PromptReadError as exc:
                self._error(400, f"the stand-in reads only the planner's prompt: {exc}", "invalid_request_error")
                return
            self._complete(model, content, n_in)

        def _complete(self, model: str, content: str, n_in: int) -> None:
            """A chat.completion answer with its usage, counted in the server's stats."""
            n_out = text_tokens(content)
            server.count(n_in, n_out)
            self._send(200, {
                "id": f"chatcmpl-standin-{server.stats.requests}", "object": "chat.completion",
                "created": int(time.time()), "model": model,
                "choices": [{"index": 0, "finish_reason": "stop",
                             "message": {"role": "assistant", "content": content}}],
                "usage": {"prompt_tokens": n_in, "completion_tokens": n_out, "total_tokens": n_in + n_out},
            })

    return Handler


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=0, help="0: a free port (printed)")
    ap.add_argument("--latency-s", type=float, default=2.0)
    ap.add_argument("--latency-dist", choices=["fixed", "uniform", "lognormal"], default="fixed")
    ap.add_argument("--latency-spread", type=float, default=0.3)
    ap.add_argument("--policy", choices=sorted(STANDIN_POLICIES), default="heuristic")
    ap.add_argument("--stop-after", type=int, default=6)
    ap.add_argument("--error-rate-429", type=float, default=0.0)
    ap.add_argument("--error-rate-500", type=float, default=0.0)
    ap.add_argument("--timeout-rate", type=float, default=0.0)
    ap.add_argument("--retry-after-s", type=float, default=1.0)
    ap.add_argument("--timeout-sleep-s", type=float, default=120.0)
    ap.add_argument("--fault-script", default="", help="comma-separated outcomes of the first requests")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--emulate", choices=["none", *sorted(EMULATIONS)], default="none",
                    help="enforce that server's image limit, context window, parameters and error bodies")
    ap.add_argument("--max-images", type=int, default=None, help="the emulated image limit (vLLM's "
                    "--limit-mm-per-prompt); default: the server's")
    ap.add_argument("--context-tokens", type=int, default=None, help="the emulated window (vLLM's "
                    "--max-model-len, Ollama's num_ctx); default: the server's")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    cfg = StandinConfig(
        latency_s=a.latency_s, latency_dist=a.latency_dist, latency_spread=a.latency_spread, policy=a.policy,
        stop_after=a.stop_after, error_rate_429=a.error_rate_429, error_rate_500=a.error_rate_500,
        timeout_rate=a.timeout_rate, retry_after_s=a.retry_after_s, timeout_sleep_s=a.timeout_sleep_s,
        fault_script=[f for f in a.fault_script.split(",") if f], seed=a.seed, emulate=a.emulate,
        emulate_max_images=a.max_images, emulate_context_tokens=a.context_tokens)
    with StandinServer(cfg, a.host, a.port) as srv:
        log.info("llm stand-in (%s, %.2f s %s) listening on %s", cfg.policy, cfg.latency_s, cfg.latency_dist,
                 srv.url)
        print(srv.url, flush=True)  # the one line a launching script reads
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
