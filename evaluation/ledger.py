"""The cost ledger of a run: tokens, dollars and seconds per stage, per step and per episode; the
estimate of a run's tokens and dollars before any API call; the budget that stops a run.

Per step the ledger reads the mission's step events (``MissionStep``: the decision's tokens and dollars,
the loop's ``timings_s``); each step's timings hold the move and observation that led to it, then the
candidates, anticipated views, spatial map and policy call of the step itself (see the planner's
mission loop). Stages are named here once, as data.

The estimate builds the planner's real prompt (:class:`PromptBuilder`) for every step an episode is
expected to take, with placeholder images of the prompt's sizes, and counts it with the planner's token
counter; see :func:`estimate_run` for the assumptions.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from shared.pricing import PriceTable
from shared.schemas import Candidate, CandidateKind, Pose

# Ledger stage -> the planner's step timing key.
STAGES: dict[str, str] = {
    "observe": "observe_s",
    "candidates": "candidates_s",
    "anticipation": "anticipation_s",
    "map": "spatial_map_s",
    "policy": "decide_s",
    "move": "move_s",
}

LEDGER_COLUMNS = ["prompt_tokens", "completion_tokens", "cost_usd_ep", *(f"{s}_s" for s in STAGES)]
"""Summary columns of the ledger: token totals, the mean dollars per episode, and each stage's mean
seconds per step (``cost_usd``, the total, and ``tokens``, the mean per episode, are in the base table)."""


def step_ledger(events: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """One ledger entry per mission step event (as the gateway's history returns them)."""
    out = []
    for ev in events:
        data = ev.get("data") or {}
        if ev.get("kind") != "step" or data.get("type") != "mission_step":
            continue
        dec = data.get("decision") or {}
        timings = data.get("timings_s") or {}
        out.append({
            "step": int(ev.get("step", len(out))),
            "prompt_tokens": int(dec.get("prompt_tokens", 0)),
            "completion_tokens": int(dec.get("completion_tokens", 0)),
            "cost_usd": float(dec.get("cost_usd", 0.0)),
            "stage_s": {stage: float(timings.get(key, 0.0)) for stage, key in STAGES.items()},
        })
    return out


def stage_totals(steps: Sequence[dict[str, Any]]) -> dict[str, float]:
    """Seconds per stage summed over an episode's steps."""
    return {s: round(sum(float(st["stage_s"].get(s, 0.0)) for st in steps), 4) for s in STAGES}


def ledger_row(done: Sequence[Any]) -> dict[str, Any]:
    """The ledger's summary fields over finished episodes (objects with the EpisodeResult fields)."""
    row: dict[str, Any] = {c: None for c in LEDGER_COLUMNS}
    if not done:
        return row
    row["prompt_tokens"] = int(sum(r.prompt_tokens for r in done))
    row["completion_tokens"] = int(sum(r.completion_tokens for r in done))
    row["cost_usd_ep"] = round(float(np.mean([r.cost_usd for r in done])), 5)
    steps = [st for r in done for st in (getattr(r, "ledger", None) or [])]
    if steps:
        for s in STAGES:
            row[f"{s}_s"] = round(float(np.mean([st["stage_s"].get(s, 0.0) for st in steps])), 4)
    return row


def ledger_markdown(done: Sequence[Any], stopped: str = "", spent: Spent | None = None) -> str:
    """The ledger section of summary.md: totals and means per episode and per step; ``stopped``: why the
    run ended early; ``spent``: what every attempt of the run spent (finished or not)."""
    lines = ["", "## Cost ledger", ""]
    if stopped:
        lines += [f"**Run stopped early:** {stopped}", ""]
    if spent is not None:
        kept = sum((Spent.of(r) for r in done), Spent())
        lines += [f"Spent by the run, every attempt counted: ${spent.usd:.4f}, {spent.tokens:,d} tokens "
                  f"(of which ${max(0.0, spent.usd - kept.usd):.4f}, {max(0, spent.tokens - kept.tokens):,d} "
                  "tokens on attempts that did not finish: stopped by the budget, errors, retries).", ""]
    if not done:
        return "\n".join(lines + ["No finished episodes.", ""])
    n_ep = len(done)
    steps = [st for r in done for st in (getattr(r, "ledger", None) or [])]
    n_st = max(1, len(steps))
    pt, ct = sum(r.prompt_tokens for r in done), sum(r.completion_tokens for r in done)
    usd = sum(r.cost_usd for r in done)
    lines += ["| quantity | total | mean per episode | mean per step |", "|---|---:|---:|---:|",
              f"| prompt tokens | {pt} | {pt / n_ep:.0f} | {pt / n_st:.0f} |",
              f"| completion tokens | {ct} | {ct / n_ep:.0f} | {ct / n_st:.0f} |",
              f"| dollars | {usd:.4f} | {usd / n_ep:.4f} | {usd / n_st:.5f} |"]
    for s in STAGES:
        tot = sum(st["stage_s"].get(s, 0.0) for st in steps)
        lines.append(f"| {s} s | {tot:.2f} | {tot / n_ep:.3f} | {tot / n_st:.4f} |")
    lines.append(f"\n{n_ep} finished episodes, {len(steps)} steps with a ledger entry.")
    return "\n".join(lines) + "\n"


# --- budget ---------------------------------------------------------------------------------------

@dataclass
class Spent:
    """Dollars and LLM tokens (prompt + completion) spent."""

    usd: float = 0.0
    tokens: int = 0

    def __add__(self, other: Spent) -> Spent:
        return Spent(self.usd + other.usd, self.tokens + other.tokens)

    @classmethod
    def of(cls, r: Any) -> Spent:
        """What one episode attempt (an EpisodeResult, or a gateway mission record) spent."""
        get = r.get if isinstance(r, dict) else lambda k, d=0: getattr(r, k, d)
        return cls(max(0.0, float(get("cost_usd", 0.0) or 0.0)),
                   max(0, int(get("prompt_tokens", 0) or 0)) + max(0, int(get("completion_tokens", 0) or 0)))


class Budget:
    """The limits of a run, checked while episodes run, not only between them.

    - ``limit_usd`` / ``limit_tokens`` cap what the run folder has spent: every attempt logged in its
      ``results.jsonl`` (an episode stopped by the budget, or retried after an error, keeps what its
      earlier attempt spent) plus the running totals of the missions in flight, as the gateway reports
      them step by step (:meth:`track`). A mission is cancelled at the first poll that sees the limit
      reached, so a run overshoots by at most the LLM calls already in flight (one per robot).
    - ``limit_wall_s`` caps the wall seconds of this call (a resumed run gets its own), read from ``clock``
      (a test gives one that moves with the missions' steps, so the limit falls mid-episode whatever the load).

    Thread-safe: the robots' workers track their missions, the runner's thread settles results."""

    def __init__(self, limit_usd: float | None = None, limit_tokens: int | None = None,
                 limit_wall_s: float | None = None, spent: Spent | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.limit_usd, self.limit_tokens, self.limit_wall_s = limit_usd, limit_tokens, limit_wall_s
        self._settled = spent or Spent()
        self._live: dict[str, Spent] = {}
        self._lock = threading.Lock()
        self._clock = clock
        self._t0 = clock()

    @property
    def limited(self) -> bool:
        return any(x is not None for x in (self.limit_usd, self.limit_tokens, self.limit_wall_s))

    def track(self, mission_id: str, spent: Spent) -> str:
        """A mission's running totals; returns :meth:`exceeded` with them counted."""
        with self._lock:
            self._live[mission_id] = spent
        return self.exceeded()

    def settle(self, mission_id: str | None, spent: Spent) -> None:
        """An attempt is logged: its final totals replace its running ones."""
        with self._lock:
            if mission_id is not None:
                self._live.pop(mission_id, None)
            self._settled = self._settled + spent

    @property
    def spent(self) -> Spent:
        with self._lock:
            return sum(self._live.values(), self._settled)

    def exceeded(self) -> str:
        """Which limit is reached, in words ("" while none is)."""
        s = self.spent
        if self.limit_usd is not None and s.usd >= self.limit_usd:
            return f"the budget of ${self.limit_usd:.4f} was reached (${s.usd:.4f} spent)"
        if self.limit_tokens is not None and s.tokens >= self.limit_tokens:
            return f"the budget of {self.limit_tokens:,d} tokens was reached ({s.tokens:,d} spent)"
        if self.limit_wall_s is not None and self._clock() - self._t0 >= self.limit_wall_s:
            return f"the wall-time budget of {self.limit_wall_s:g} s was reached"
        return ""

    @staticmethod
    def reason(why: str, stopped: int, not_run: int) -> str:
        """The run's stop, for the summary and the console."""
        return (f"{why}; {stopped} episodes were stopped mid-way and {not_run} were not started (raise the "
                "budget and run the same command to resume: those episodes run again)")


# --- estimate -------------------------------------------------------------------------------------

@dataclass
class Estimate:
    """Expected usage of a run, before any call."""

    model: str
    episodes: int
    steps: int
    prompt_tokens: int
    completion_tokens: int
    cost_usd: float
    priced: bool
    assumptions: dict[str, Any] = field(default_factory=dict)

    def lines(self) -> list[str]:
        out = [
            f"estimate for {self.episodes} episodes, {self.steps} LLM calls, model {self.model}"
            + ("" if self.priced else " (no price in the table: dollars shown as 0)"),
            f"  prompt tokens     {self.prompt_tokens:>12,d}  ({self.prompt_tokens / max(1, self.steps):,.0f} per call)",
            f"  completion tokens {self.completion_tokens:>12,d}",
            f"  dollars           {self.cost_usd:>12.2f}  ({self.cost_usd / max(1, self.episodes):.4f} per episode)",
            "  assuming " + ", ".join(f"{k}={v}" for k, v in self.assumptions.items()),
        ]
        return out


def path_length_m(points: Sequence[Sequence[float]]) -> float:
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def estimate_run(episodes: Sequence[Any], *, model: str, prices: PriceTable, max_steps: int,
                 anticipation: bool = True, spatial_map: bool = True, waypoints: int = 4, step_m: float = 2.0,
                 completion_tokens_per_call: int = 60, detail: str = "auto", image_px: int = 256,
                 policy_config: dict[str, Any] | None = None) -> Estimate:
    """Tokens and dollars of a run from the prompt sizes.

    Assumptions (printed with the estimate): an episode takes ``ceil(reference path / step_m) + 1`` steps
    (the last is the stop; at most ``max_steps``); every step offers ``waypoints`` waypoints, a backtrack
    after the first step, and stop; every history step is kept (no forward run merged: an upper bound on
    history); one call per step (no re-asks, no retries); ``completion_tokens_per_call`` answer tokens (a
    reasoning model's hidden reasoning tokens come on top). ``policy_config`` (the openai policy's) sets the
    layout, image limits and image-token rule of its provider profile, as the policy would send them (the
    context budget's compression is not modelled: an upper bound)."""
    from services.planner.core.context import Ablation, StepContext, build_candidate_views
    from services.planner.core.history import ActionKind, ActionRecord, HistoryItem
    from services.planner.core.prompt import PromptBuilder
    from services.planner.core.tokens import prompt_tokens

    from services.planner.core.prompt import PromptConfig
    from services.planner.core.providers import profile

    pc = policy_config or {}
    prof = profile(pc.get("profile", "openai"), pc.get("profile_overrides") or {})
    images = pc.get("max_images_per_prompt") or prof.max_images_per_prompt
    builder = PromptBuilder(PromptConfig(layout=pc.get("layout", "auto"), max_images_per_prompt=images,
                                         max_image_px=pc.get("max_image_px") or prof.max_image_px,
                                         image_token_rule=prof.image_token_rule))
    rule = prof.image_token_rule
    if not prof.supports_detail:
        detail = "auto"
    img = np.zeros((image_px, image_px, 3), np.uint8)  # only the size is counted
    ablation = Ablation(anticipation=anticipation, spatial_map=spatial_map)
    pose = Pose(position_m=(0.0, 0.0, 0.0))
    n_in = n_out = calls = 0
    per_step_cache: dict[tuple[str, int], int] = {}
    for e in episodes:
        steps = min(max_steps, math.ceil(path_length_m(e.reference_path_m) / step_m) + 1)
        for s in range(steps):
            key = (e.instruction, s)
            if key not in per_step_cache:
                cands = [Candidate(index=i, dx_m=step_m * math.cos(i), dy_m=step_m * math.sin(i),
                                   angle_rad=float(math.remainder(i, 2 * math.pi)), distance_m=step_m)
                         for i in range(waypoints)]
                if s > 0:
                    cands.append(Candidate(index=len(cands), kind=CandidateKind.BACKTRACK, dx_m=-step_m,
                                           angle_rad=math.pi, distance_m=step_m))
                cands.append(Candidate(index=len(cands), kind=CandidateKind.STOP))
                views = build_candidate_views(cands, None)
                for v in views:
                    v.observed_rgb = img
                    if v.kind != CandidateKind.STOP:
                        v.anticipated_rgb = img
                history = [HistoryItem(k, img, ActionRecord(ActionKind.FORWARD, 0.0, step_m)) for k in range(s)]
                ctx = StepContext(instruction=e.instruction, step=s, pose=pose, candidates=views, history=history,
                                  spatial_map_rgb=img if spatial_map else None, ablation=ablation,
                                  max_steps=max_steps)
                per_step_cache[key] = prompt_tokens(builder.build(ctx), detail, rule)
            n_in += per_step_cache[key]
            n_out += completion_tokens_per_call
            calls += 1
    price = prices.lookup(model)
    cost = (price or prices.price(model)).cost_usd(n_in, n_out)
    return Estimate(model, len(episodes), calls, n_in, n_out, cost, price is not None, {
        "step_m": step_m, "waypoints": waypoints, "completion_tokens_per_call": completion_tokens_per_call,
        "image_px": image_px, "detail": detail, "anticipation": anticipation, "spatial_map": spatial_map,
        "profile": pc.get("profile", "openai"), "layout": pc.get("layout", "auto"), "image_rule": rule})
