"""A budget reached mid-episode on the real system: two robots (launcher processes: router, a robot-io and
a gateway per robot, the shared services), the planner's openai policy talking to the LLM stand-in (a real
HTTP server), the runner through both gateways. The missions in flight are cancelled through their
gateways and recorded as stopped; the resumed run runs them again."""

from __future__ import annotations

import json

import pytest

from evaluation.cli import main
from evaluation.dataset import SetSpec, generate_set, write_set
from evaluation.results import ResultsLog
from services.planner.tools.llm_standin import StandinConfig, StandinServer
from tests.e2e.test_eval import CURATED_DENSITY_PER_M2  # sparse: the maps' density is not what is tested

pytestmark = [pytest.mark.e2e, pytest.mark.system]

CALLS_PER_EPISODE = 4  # the stand-in's ``straight`` policy answers stop at this step
# Small houses: the budget and the resume do not depend on a house's size, and each robot's scene switch and
# curated cloud (built, uploaded, indexed) cost seconds more for the default house (call 48 -> 22 s at load
# average 4.4; CPU of the file, the session system included, 53 -> 34 s).
AREA_M2 = 60.0


def test_a_budget_cancels_the_missions_in_flight_and_the_resumed_run_reruns_them(tmp_path, capsys,
                                                                                 system_on_scene):
    ds, gt = generate_set(SetSpec(houses=2, per_house=1, floors=(1,), seed=3, area_m2=AREA_M2), with_gt=True)
    episodes = write_set(ds, gt, tmp_path / "set.json.gz")[0]
    out = tmp_path / "out"
    # The session's launched system (tests/conftest.py: two robots); the runner switches both robots'
    # scenes, and ``system_on_scene`` puts them back afterwards.
    launcher = system_on_scene
    assert len(launcher.gateway_urls) == 2
    # 1 s per call: the runner sees a step's tokens long before the mission could end.
    with StandinServer(StandinConfig(latency_s=1.0, policy="straight", stop_after=CALLS_PER_EPISODE)) as llm:
        policy = {"model": "gpt-4o-mini", "base_url": llm.url, "api_key": "test"}
        argv = ["run", "--episodes", str(episodes), "--out", str(out), "--policy", "openai",
                "--policy-config", json.dumps(policy), "--map-source", "curated", "--max-steps", "8",
                "--no-anticipation", "--no-spatial-map", "--mission-timeout-s", "240", "--no-progress",
                "--curated-density-per-m2", CURATED_DENSITY_PER_M2,
                *[x for url in launcher.gateway_urls for x in ("--gateway", url)]]
        # One token: the first step of any robot reaches it.
        assert main([*argv, "--budget-tokens", "1"]) == 0
        first = ResultsLog(out / "results.jsonl").load()
        text = capsys.readouterr().out
        calls_first = llm.stats.by_outcome.get("ok", 0)
        assert first and {r.status for r in first.values()} == {"stopped"}, {k: r.reason for k, r in first.items()}
        for r in first.values():
            assert r.state == "cancelled" and "budget of 1 tokens was reached" in r.reason
            assert len(r.ledger) < CALLS_PER_EPISODE  # cancelled mid-way (or before its first step)
        # The mission whose step reached the budget was paid for that step (the other robot's, if it
        # was running then, is cancelled wherever it stood).
        assert max(len(r.ledger) for r in first.values()) >= 1
        assert sum(r.prompt_tokens for r in first.values()) > 0
        assert calls_first < 2 * CALLS_PER_EPISODE
        assert "stopped early: the budget of 1 tokens was reached" in text and "| 0 | 0 | 0 |" in text
        md = (out / "summary.md").read_text()
        assert "Run stopped early" in md and "episodes were stopped mid-way" in md
        spent_first = sum(r.prompt_tokens + r.completion_tokens for r in first.values())

        # Resumed without a budget: the stopped episodes run again, to their end. The stand-in now answers
        # at once: the 1 s per call was for the budget to land mid-episode, and nothing is cancelled now;
        # at 1 s the resume spent ~4 s of the tier's longest worker waiting (4 calls a robot, both at once).
        llm.config = llm.config.model_copy(update={"latency_s": 0.0})
        assert main(argv) == 0
        final = ResultsLog(out / "results.jsonl").load()
        text = capsys.readouterr().out
    assert sorted(final) == ["1", "2"] and all(r.status == "done" for r in final.values()), \
        {k: r.reason for k, r in final.items()}
    assert all(len(r.ledger) == CALLS_PER_EPISODE for r in final.values())
    assert "2 episodes run, 0 resumed" in text  # stopped and not started: both run now
    # What the stopped attempts spent is part of the run's spending.
    spent_all = spent_first + sum(r.prompt_tokens + r.completion_tokens for r in final.values())
    assert f"{spent_all:,d} tokens" in text
    assert "Run stopped early" not in (out / "summary.md").read_text()
