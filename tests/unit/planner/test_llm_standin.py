"""The OpenAI-compatible stand-in (services/planner/tools/llm_standin.py) against the real openai policy.

A real HTTP server on 127.0.0.1; the planner's openai backend talks to it through the openai SDK, so the
retries, backoff and Retry-After handling are the production code paths.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest
from tests.unit.planner.planner_toyworld import ToyWorld, run_episode

from services.planner.core import POLICIES, OpenAIConfig
from services.planner.core.tokens import image_tokens, text_tokens
from services.planner.tools.llm_standin import StandinConfig, StandinServer, read_action
from shared.schemas import CandidateKind

pytestmark = pytest.mark.timeout(90)

INSTRUCTION = "Walk forward 3 meters, turn left and walk 3 meters, then stop."


def _world(labels=False):
    return ToyWorld(landmarks={"sofa": (5.0, 0.0)}, rooms={}, with_labels=labels)


def _cfg(url, **kw):
    base = dict(model="gpt-4o-mini", base_url=url, api_key="test", timeout_s=5.0, retries=0,
                backoff_initial_s=0.01, backoff_max_s=0.05, on_error="raise")
    base.update(kw)
    return OpenAIConfig(**base)


def _fast(**kw):
    return StandinConfig(**{"latency_s": 0.0, **kw})


def test_token_counts_follow_the_prompt():
    assert text_tokens("") == 0
    assert text_tokens("walk to the sofa.") == 5  # four short words and a full stop
    assert text_tokens("internationalisation") == 5  # 20 characters, ceil(20 / 4)
    assert image_tokens(256, 256) == 255 and image_tokens(256, 256, "low") == 85
    assert image_tokens(1024, 1024) == 85 + 170 * 4  # scaled to 768 x 768: 2 x 2 tiles
    assert read_action("turn right 60 degrees and move 1.5 m").angle_rad == pytest.approx(-1.0472, abs=1e-3)
    assert read_action("go back to the previous position (2.0 m away)").kind == CandidateKind.BACKTRACK


def test_heuristic_standin_answers_as_the_planner_heuristic_does():
    """Without labels the heuristic navigates by turns and distances, which the prompt text carries in
    full: the stand-in's answers (read back from the prompt) equal the in-process policy's."""
    with POLICIES.create("heuristic") as local:
        ref_traj, ref_stop, ref = run_episode(_world(), local, INSTRUCTION, max_steps=8)
    with StandinServer(_fast()) as srv, POLICIES.create("openai", _cfg(srv.url)) as policy:
        traj, stop, got = run_episode(_world(), policy, INSTRUCTION, max_steps=8)
        usage = policy.usage
    assert [d.candidate_index for d in got] == [d.candidate_index for d in ref]
    assert stop == ref_stop and traj.shape == ref_traj.shape
    assert not any(d.fallback for d in got)
    # Tokens are the request's own: every step carries images (255 tokens each at 256 px) and more text as
    # the history grows, so later prompts cost more.
    assert usage.calls == len(got) and usage.prompt_tokens == srv.stats.prompt_tokens
    assert got[0].prompt_tokens > 3 * 255 and got[-1].prompt_tokens > got[0].prompt_tokens
    assert usage.cost_usd == pytest.approx((usage.prompt_tokens * 0.15 + usage.completion_tokens * 0.6) / 1e6)


def test_retry_survives_429_500_and_timeout_and_honours_retry_after(caplog):
    cfg = _fast(fault_script=["429", "500", "timeout"], retry_after_s=0.25, timeout_sleep_s=2.0)
    with StandinServer(cfg) as srv, POLICIES.create("openai", _cfg(srv.url, retries=3, timeout_s=0.5)) as policy:
        t0 = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="services.planner.core.openai_policy"):
            _, _, decisions = run_episode(_world(), policy, INSTRUCTION, max_steps=1)
        elapsed = time.monotonic() - t0
    assert not decisions[0].fallback
    assert srv.stats.by_outcome == {"429": 1, "500": 1, "timeout": 1, "ok": 1}
    # The 429 said "retry after 0.25 s"; the backoff alone would have waited at most 0.075 s. The waits the
    # client chose are read from its log (they do not depend on load), and the run's time is a lower bound.
    waits_s = [float(r.args[2]) for r in caplog.records if "retrying in" in r.msg]
    assert len(waits_s) == 3 and waits_s[0] >= 0.25 and max(waits_s[1:]) <= 0.075
    assert elapsed >= 0.25 + 0.5


def test_sampled_faults_over_an_episode_never_reach_the_fallback():
    cfg = _fast(policy="straight", stop_after=5, error_rate_429=0.25, error_rate_500=0.25, retry_after_s=0.0,
                seed=3)
    with StandinServer(cfg) as srv, POLICIES.create("openai", _cfg(srv.url, retries=8)) as policy:
        _, stopped, decisions = run_episode(_world(), policy, INSTRUCTION, max_steps=10)
    assert stopped and len(decisions) == 5 and not any(d.fallback for d in decisions)
    assert srv.stats.by_outcome.get("429", 0) + srv.stats.by_outcome.get("500", 0) > 0
    assert srv.stats.by_outcome["ok"] == 5


def test_exhausted_retries_fall_back_and_bad_requests_get_400():
    cfg = _fast(fault_script=["500", "500"])
    with StandinServer(cfg) as srv:
        with POLICIES.create("openai", _cfg(srv.url, retries=1, on_error="fallback")) as policy:
            _, _, decisions = run_episode(_world(), policy, INSTRUCTION, max_steps=1)
        assert decisions[0].fallback and "InternalServerError" in decisions[0].reasoning
        req = urllib.request.Request(srv.url + "/chat/completions", data=b'{"messages": "nope"}',
                                     headers={"Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(req, timeout=5)
        assert err.value.code == 400
        not_planner = json.dumps({"model": "m", "messages": [{"role": "user", "content": "hi"}]}).encode()
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(urllib.request.Request(srv.url + "/chat/completions", data=not_planner), timeout=5)
        assert err.value.code == 400
        # Still serving after both.
        with POLICIES.create("openai", _cfg(srv.url)) as policy:
            _, _, decisions = run_episode(_world(), policy, INSTRUCTION, max_steps=1)
        assert not decisions[0].fallback


@pytest.mark.system  # the stand-in as its own process
def test_command_line_server_with_latency():
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.planner.tools.llm_standin", "--port", "0", "--latency-s", "0.3",
         "--policy", "straight", "--stop-after", "2"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:") and url.endswith("/v1")
        with POLICIES.create("openai", _cfg(url)) as policy:
            t0 = time.monotonic()
            _, stopped, decisions = run_episode(_world(), policy, INSTRUCTION, max_steps=5)
            elapsed = time.monotonic() - t0
        assert stopped and len(decisions) == 2
        assert elapsed >= 2 * 0.3  # each call waited the configured latency
    finally:
        proc.terminate()
        proc.wait(timeout=10)
