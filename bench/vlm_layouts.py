"""bench/vlm_layouts: prompt tokens per step for each image layout, and dollars per 100 episodes (issue 35).

The step prompt as the planner builds it (256 px candidate views, observed + anticipated; 256 px history
frames; a 512 px spatial map) for 4, 6 and 8 waypoints (+ backtrack and stop), along an episode of
``--steps`` steps whose history grows one item per step up to the builder's 16. Tokens are counted with
the planner's own counter (:mod:`services.planner.core.tokens`, OpenAI's exact image-tile rule, and the
Qwen2.5-VL patch rule for local servers). Dollars use the repo's price table (shared/pricing.py: GPT-5.1
at $1.25 / $10 per 1M input / output tokens, OpenAI's published list price) with ``--completion-tokens``
per step (a JSON answer; reasoning tokens excluded, as with reasoning_effort=none).

The decisions are then checked: the same steps are sent to the stand-in (``heuristic`` policy, a real HTTP
server) in both layouts and must be identical.

    .venv/bin/python -m bench.vlm_layouts
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from bench.common import table
from services.planner.core import (
    POLICIES,
    ActionKind,
    ActionRecord,
    HistoryRecorder,
    OpenAIConfig,
    PromptBuilder,
    PromptConfig,
    StepContext,
    build_candidate_views,
    with_stop_and_backtrack,
)
from services.planner.core.tokens import prompt_tokens
from services.planner.tools.llm_standin import StandinConfig, StandinServer
from shared.geometry import panorama_headings
from shared.pricing import PriceTable
from shared.schemas import Candidate, CameraIntrinsics, Panorama, Pose, RenderResult

LAYOUTS = ("separate", "mosaic")


def _noise(rng: np.random.Generator, px: int) -> np.ndarray:
    # Noise, not flat colour: JPEG sizes and any content-dependent path see a realistic image.
    return rng.integers(0, 256, (px, px, 3), dtype=np.uint8)


def synthetic_context(n_waypoints: int, step: int, seed: int = 0, history_px: int = 256) -> StepContext:
    """A step with ``n_waypoints`` waypoints spread around the agent, backtrack and stop, and ``step``
    history items (one per earlier step)."""
    rng = np.random.default_rng(seed + 1000 * n_waypoints + step)
    pose = Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0)
    heads = panorama_headings(0.0)
    pano = Panorama(pose=pose, camera=CameraIntrinsics(width_px=256, height_px=256), headings_rad=heads,
                    rgb=np.stack([_noise(rng, 256) for _ in range(12)]), depth_m=np.ones((12, 256, 256), np.float32))
    wps = []
    for k in range(n_waypoints):
        a = math.remainder(2 * math.pi * k / n_waypoints, 2 * math.pi)
        d = 1.5 + 0.25 * (k % 3)
        wps.append(Candidate(index=k, dx_m=d * math.cos(a), dy_m=d * math.sin(a), angle_rad=a, distance_m=d))
    cands = with_stop_and_backtrack(wps, pose, (-1.0, 0.0, 0.0) if step else None)
    movable = [c for c in cands if c.kind.value != "stop"]
    render = RenderResult(map_id="m", version=1, rgb=np.stack([_noise(rng, 256) for _ in movable]),
                          depth_m=np.ones((len(movable), 256, 256), np.float32),
                          hole_mask=np.zeros((len(movable), 256, 256), bool))
    rec = HistoryRecorder()
    for s in range(step):
        # Alternating turns keep every item its own (forward runs would be merged by the compression).
        rec.record(s, _noise(rng, history_px), ActionRecord(ActionKind.TURN_MOVE, 0.6 if s % 2 else -0.6, 1.5))
    return StepContext(instruction="Walk past the sofa into the kitchen, turn left and stop by the fridge.",
                       step=step, pose=pose, candidates=build_candidate_views(cands, pano, render),
                       history=rec.compressed(), spatial_map_rgb=_noise(rng, 512), mission_id="bench",
                       max_steps=40)


def episode_tokens(n_waypoints: int, layout: str, steps: int, rule: str) -> list[int]:
    builder = PromptBuilder(PromptConfig(layout=layout, image_token_rule=rule))
    return [prompt_tokens(builder.build(synthetic_context(n_waypoints, s)), "auto", rule) for s in range(steps)]


def decisions_match(n_waypoints: int, steps: int) -> tuple[bool, int]:
    """The stand-in's decisions for the same steps in both layouts: (identical, steps compared)."""
    got = {}
    with StandinServer(StandinConfig(latency_s=0.0)) as srv:
        for layout in LAYOUTS:
            cfg = OpenAIConfig(model="gpt-5.1", base_url=srv.url, api_key="bench", layout=layout, retries=0,
                               on_error="raise", profile="generic")
            with POLICIES.create("openai", cfg) as policy:
                policy.reset(f"bench-{layout}")
                got[layout] = [policy.decide(synthetic_context(n_waypoints, s)).candidate_index for s in range(steps)]
    return got["separate"] == got["mosaic"], steps


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser()
    ap.add_argument("--waypoints", type=int, nargs="+", default=[4, 6, 8])
    ap.add_argument("--steps", type=int, default=12, help="steps per episode (history grows by one a step)")
    ap.add_argument("--completion-tokens", type=int, default=60, help="answer tokens per step")
    ap.add_argument("--model", default="gpt-5.1")
    a = ap.parse_args(argv)
    price = PriceTable().price(a.model)
    rows, out = [], {}
    for n in a.waypoints:
        res = {layout: episode_tokens(n, layout, a.steps, "openai_tiles") for layout in LAYOUTS}
        qwen = {layout: episode_tokens(n, layout, a.steps, "qwen_patches") for layout in LAYOUTS}
        usd = {layout: 100 * sum(price.cost_usd(t, a.completion_tokens) for t in res[layout]) for layout in LAYOUTS}
        mean = {layout: float(np.mean(res[layout])) for layout in LAYOUTS}
        same, k = decisions_match(n, min(a.steps, 6))
        ratio = mean["mosaic"] / mean["separate"]
        out[n] = {"mean": mean, "usd": usd, "ratio": ratio, "same": same}
        rows.append((n, res["separate"][0], res["separate"][-1], round(mean["separate"]), res["mosaic"][0],
                     res["mosaic"][-1], round(mean["mosaic"]), f"{100 * ratio:.1f} %",
                     f"{100 * np.mean(qwen['mosaic']) / np.mean(qwen['separate']):.0f} %",
                     f"{usd['separate']:.2f}", f"{usd['mosaic']:.2f}", f"{'same' if same else 'DIFFER'} ({k} steps)"))
    table(f"Prompt tokens per step (OpenAI tile rule), {a.steps}-step episodes; $ per 100 episodes at {a.model} "
          f"(${price.input_per_1m_usd}/${price.output_per_1m_usd} per 1M, {a.completion_tokens} answer tokens/step)",
          rows, ("waypoints", "separate step 1", f"separate step {a.steps}", "separate mean", "mosaic step 1",
                 f"mosaic step {a.steps}", "mosaic mean", "mosaic/separate", "mosaic/separate (Qwen rule)",
                 "$/100 ep separate", "$/100 ep mosaic", "stand-in decisions"))
    return out


if __name__ == "__main__":
    main()
