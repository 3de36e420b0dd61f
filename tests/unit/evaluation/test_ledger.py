"""The cost ledger: per-step and per-episode tokens, dollars and stage seconds in the results and summary;
the budget that stops a run; the estimate; price tables."""

from __future__ import annotations

import csv
import json
import math
import time

import numpy as np
import pytest

from evaluation.cli import main as cli_main
from evaluation.ledger import STAGES, estimate_run
from evaluation.runner import EvalRunner, RunConfig
from services.planner.core import Ablation, PromptBuilder, StepContext, build_candidate_views
from services.planner.core.tokens import message_tokens, prompt_tokens
from shared.pricing import PriceTable, PriceTableError
from shared.schemas import Candidate, CandidateKind, Pose
from tests.doubles.scripted_eval import SCRIPTED_TIMINGS_S
from tests.unit.evaluation.conftest import box_scene, make_episode


def _runner(gw, world, out, clock=time.monotonic, **cfg):
    return EvalRunner(gw, world.robot, RunConfig(poll_s=0.01, plots=False, **cfg), out, progress=False,
                      scene_builder=lambda spec, d: box_scene(), clock=clock)


def _eps(n=3):
    return [make_episode(i, "generated:1", goal=(4.0, 0.0, 0.0)) for i in range(1, n + 1)]


def test_ledger_per_step_per_episode_and_in_both_summaries(world, gateway, tmp_path):
    out = tmp_path / "out"
    with gateway() as gw:
        report = _runner(gw, world, out, max_steps=10).run(_eps(2))
    for r in report.results:
        # 4 m at 1 m per step, then the stop: 5 steps, each with its scripted tokens, dollars and timings.
        assert [s["step"] for s in r.ledger] == [1, 2, 3, 4, 5]
        assert all(s["prompt_tokens"] == 100 and s["cost_usd"] == pytest.approx(0.0005) for s in r.ledger)
        assert r.stage_s == {stage: pytest.approx(5 * SCRIPTED_TIMINGS_S[key]) for stage, key in STAGES.items()}
    row = report.row
    assert row["prompt_tokens"] == 1000 and row["completion_tokens"] == 100
    assert row["cost_usd"] == pytest.approx(0.005) and row["cost_usd_ep"] == pytest.approx(0.0025)
    assert row["move_s"] == pytest.approx(0.06) and row["map_s"] == pytest.approx(0.04)
    md = (out / "summary.md").read_text()
    assert "## Cost ledger" in md and "| prompt tokens | 1000 | 500 | 100 |" in md and "| move s |" in md
    with open(out / "summary.csv") as f:
        line = next(csv.DictReader(f))
    assert line["prompt_tokens"] == "1000" and float(line["policy_s"]) == pytest.approx(0.05)


def test_budget_stops_the_run_mid_episode_and_the_run_resumes(world, gateway, tmp_path):
    out = tmp_path / "out"
    world.planner.interval_s = 0.05  # steps take time, as a real planner's do: the runner polls in between
    with gateway() as gw:
        # Each step costs $0.0005, an episode 5 steps: episode 1 spends $0.0025, episode 2 reaches $0.004
        # at its third step and is cancelled there; episode 3 never starts.
        first = _runner(gw, world, out, budget_usd=0.004).run(_eps(3))
        assert first.ran == 2 and len(world.planner.requests) == 2
        done, stopped = first.results
        assert done.status == "done" and stopped.status == "stopped" and stopped.metrics is None
        assert stopped.state == "cancelled" and "stopped mid-way: the budget of $0.0040 was reached" in stopped.reason
        assert 3 <= len(stopped.ledger) < 5  # cancelled between steps, before its own end
        assert "1 episodes were stopped mid-way and 1 were not started" in first.stopped
        assert first.row["count"] == 1 and first.row["stopped"] == 1 and first.row["errors"] == 0
        assert first.spent.usd == pytest.approx(0.0025 + stopped.cost_usd) and first.spent.usd < 0.004 + 0.0005 + 1e-9
        md = (out / "summary.md").read_text()
        assert "Run stopped early" in md and "Spent by the run, every attempt counted: $" in md
        # Resumed with a larger budget: the stopped episode runs again, and what its first attempt spent counts.
        # Nothing is cancelled in this run, so its steps need no time between polls.
        world.planner.interval_s = 0.0
        second = _runner(gw, world, out, budget_usd=0.012).run(_eps(3))
    assert second.ran == 2 and second.resumed == 1 and not second.stopped
    assert [r.status for r in second.results] == ["done"] * 3 and second.row["stopped"] == 0
    assert second.row["cost_usd"] == pytest.approx(0.0075)  # the kept episodes
    assert second.spent.usd == pytest.approx(0.0075 + stopped.cost_usd)  # every attempt
    assert "Run stopped early" not in (out / "summary.md").read_text()


def test_token_and_wall_time_budgets(world, gateway, tmp_path):
    world.planner.interval_s = 0.05
    # 0.25 m steps towards a goal 4 m away: an episode is 17 steps (1,870 tokens), so a poll that a busy
    # machine delays by a few steps still stops it in the middle, which is what is tested.
    world.planner.step_m = 0.25
    with gateway() as gw:
        # 110 tokens per step: 300 tokens are reached at the third step of the first episode.
        tok = _runner(gw, world, tmp_path / "tokens", budget_tokens=300).run(_eps(2))
        assert [r.status for r in tok.results] == ["stopped"] and "budget of 300 tokens was reached" in tok.stopped
        assert 330 <= tok.spent.tokens < 17 * 110
        # Wall time from a clock that moves 0.4 s per step walked: an episode takes 6.8 s of it, the run may
        # take 1.5 s, reached at the fourth step of the first episode. On the monotonic clock the budget had
        # to outlast the first mission's submission on a busy machine (a 0.3 s budget once ran out before the
        # first episode began: no result at all), which cost 1.5 s of waiting.
        wall = _runner(gw, world, tmp_path / "wall", budget_wall_s=1.5,
                       clock=lambda: 0.4 * world.planner.steps_walked).run(_eps(2))
    assert [r.status for r in wall.results] == ["stopped"] and "wall-time budget of 1.5 s" in wall.stopped
    assert 4 <= len(wall.results[0].ledger) < 17  # not before 1.6 s of the clock, and before the episode's end


def _ctx(step, n_waypoints):
    img = np.zeros((256, 256, 3), np.uint8)
    cands = [Candidate(index=i, dx_m=1.0, angle_rad=0.3 * i, distance_m=2.0) for i in range(n_waypoints)]
    cands.append(Candidate(index=len(cands), kind=CandidateKind.STOP))
    views = build_candidate_views(cands, None)
    for v in views:
        v.observed_rgb = img
        v.anticipated_rgb = img if v.kind != CandidateKind.STOP else None
    return StepContext(instruction="Walk past the sofa and stop at the door.", step=step,
                       pose=Pose(position_m=(0.0, 0.0, 0.0)), candidates=views, spatial_map_rgb=img,
                       ablation=Ablation())


def test_prompt_count_equals_the_count_of_the_messages_sent():
    """The estimate counts a Prompt without encoding images; the stand-in counts the encoded messages.
    Both must agree, or the estimate would not predict what the stand-in (or a server) bills."""
    prompt = PromptBuilder().build(_ctx(0, 3))
    assert prompt_tokens(prompt) == message_tokens(prompt.to_openai_messages("jpeg"))
    # 3 observed + 3 anticipated + stop's observed + the map: 8 images of one tile.
    assert prompt_tokens(prompt) > 8 * 255
    assert prompt_tokens(prompt, "low") == prompt_tokens(prompt) - 8 * (255 - 85)


def test_estimate_scales_with_episodes_steps_and_price():
    eps = [make_episode(1, "generated:1", goal=(4.0, 0.0, 0.0)), make_episode(2, "generated:1", goal=(8.0, 0.0, 0.0))]
    table = PriceTable()
    est = estimate_run(eps, model="gpt-4o-mini", prices=table, max_steps=40, step_m=2.0)
    assert est.steps == (math.ceil(4 / 2) + 1) + (math.ceil(8 / 2) + 1) and est.priced
    assert est.completion_tokens == 60 * est.steps
    assert est.cost_usd == pytest.approx((est.prompt_tokens * 0.15 + est.completion_tokens * 0.6) / 1e6)
    lean = estimate_run(eps, model="gpt-4o-mini", prices=table, max_steps=40, anticipation=False, spatial_map=False)
    assert lean.prompt_tokens < est.prompt_tokens  # fewer images per prompt
    capped = estimate_run(eps, model="gpt-4o-mini", prices=table, max_steps=2)
    assert capped.steps == 4
    assert not estimate_run(eps, model="my-local-llm", prices=table, max_steps=40).priced


def test_price_tables_from_files(tmp_path):
    t = PriceTable()
    assert t.price("gpt-5-mini-2025-08-07").input_per_1m_usd == 0.25  # the longest family, not gpt-5
    assert t.price("unknown").input_per_1m_usd == 0.0
    (tmp_path / "p.toml").write_text('["my-llm"]\ninput_per_1m_usd = 1.0\noutput_per_1m_usd = 2.0\n')
    (tmp_path / "p.json").write_text(json.dumps({"gpt-4o": {"input_per_1m_usd": 9, "output_per_1m_usd": 9}}))
    assert PriceTable.load(tmp_path / "p.toml").price("my-llm").cost_usd(1_000_000, 500_000) == pytest.approx(2.0)
    assert PriceTable.load(tmp_path / "p.json").price("gpt-4o").input_per_1m_usd == 9
    (tmp_path / "bad.json").write_text(json.dumps({"x": {"input_per_1m_usd": -1, "output_per_1m_usd": 0}}))
    with pytest.raises(PriceTableError):
        PriceTable.load(tmp_path / "bad.json")


def test_cli_estimate_calls_nothing(tmp_path, capsys):
    from libs.world.episodes import EpisodeDataset, write_episodes

    path = write_episodes(EpisodeDataset(episodes=_eps(4)), tmp_path / "eps.json.gz")
    (tmp_path / "prices.json").write_text(json.dumps({"gpt-4o": {"input_per_1m_usd": 2.5, "output_per_1m_usd": 10}}))
    # No gateway and no system: --estimate must not need either.
    rc = cli_main(["run", "--episodes", str(path), "--policy", "openai", "--policy-config", '{"model": "gpt-4o"}',
                   "--prices", str(tmp_path / "prices.json"), "--estimate", "--budget-usd", "0.01",
                   "--out", str(tmp_path / "out")])
    text = capsys.readouterr().out
    assert rc == 0 and "estimate for 4 episodes, 12 LLM calls, model gpt-4o" in text and "short" in text
    assert not (tmp_path / "out").exists()


def test_a_budget_reached_while_a_scene_map_is_built_cancels_the_exploration(world, gateway, tmp_path):
    out = tmp_path / "out"
    world.mapper.hold = True  # its explorations hold in their reconstructing stage until cancelled
    with gateway() as gw:
        first = _runner(gw, world, out, budget_wall_s=0.3).run(_eps(2))
        (x,) = gw.http.get("/explorations").json()["items"]
        md = (out / "summary.md").read_text()
        # Resumed without a budget: the scene is explored again (no map was kept) and its episodes run.
        world.mapper.hold = False
        second = _runner(gw, world, out).run(_eps(2))
        explorations = gw.http.get("/explorations").json()["items"]
    # Cancelled through the gateway, in whichever stage the budget found it (the scripted mapper holds in its
    # last one); the run ended cleanly, no episode begun.
    assert world.mapper.cancels == 1 and x["state"] == "cancelled"
    assert x["stage"] in ("exploring", "touring", "reconstructing")
    assert first.ran == 0 and first.results == [] and first.maps == {}
    assert "the wall-time budget of 0.3 s was reached; 0 episodes were stopped mid-way and 2 were not started" \
        in first.stopped
    assert f"the exploration {x['id']} building the map of generated:1 was cancelled while {x['stage']}" \
        in first.stopped
    assert "**Run stopped early:** " + first.stopped in md
    assert second.ran == 2 and [r.status for r in second.results] == ["done"] * 2 and not second.stopped
    assert [e["state"] for e in explorations] == ["succeeded", "cancelled"]  # newest first
