"""The planner against VLM servers' limits (issue 35): layouts, provider profiles, the context budget,
errors by kind, and one mission per profile against the stand-in emulating the matching server.

Every server here is the real stand-in HTTP server on 127.0.0.1 with ``emulate`` set; the planner's openai
backend talks to it through the openai SDK, so refusals arrive as the SDK raises them.
"""

from __future__ import annotations

import pytest
from tests.unit.planner.planner_toyworld import ToyWorld, run_episode

from bench.vlm_layouts import synthetic_context
from services.planner.core import POLICIES, OpenAIConfig, PromptBuilder, PromptConfig, ReplayConfig, parse_answer
from services.planner.core.errors import AnswerError
from services.planner.core.prompt import split_thinking
from services.planner.core.providers import (
    PROFILES,
    ContextBudgetError,
    RequestRejectedError,
    context_from_models_listing,
    is_context_overflow,
    profile,
)
from services.planner.core.tokens import prompt_tokens
from services.planner.tools.llm_standin import StandinConfig, StandinServer

pytestmark = pytest.mark.timeout(120)

INSTRUCTION = "Walk forward 3 meters, turn left and walk 3 meters, then stop."


def _world():
    return ToyWorld(landmarks={"sofa": (5.0, 0.0)}, rooms={}, with_labels=False)


def _cfg(url, **kw):
    base = dict(model="standin", base_url=url, api_key="test", timeout_s=10.0, retries=0, backoff_initial_s=0.01,
                backoff_max_s=0.05, on_error="raise", max_completion_tokens=200)
    base.update(kw)
    return OpenAIConfig(**base)


@pytest.fixture(scope="module")
def reference():
    """The heuristic's own decisions on the toy episode (the stand-in answers with the same policy)."""
    with POLICIES.create("heuristic") as local:
        _, stop, decisions = run_episode(_world(), local, INSTRUCTION, max_steps=8)
    return stop, [d.candidate_index for d in decisions]


# --- layouts ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n", [4, 6, 8])
def test_mosaic_names_every_tile_and_costs_at_most_40_percent(n):
    ctx = synthetic_context(n, step=10)
    sep = PromptBuilder(PromptConfig(layout="separate")).build(ctx)
    mos = PromptBuilder(PromptConfig(layout="mosaic")).build(ctx)
    assert len(mos.images()) == 3 and len(sep.images()) > 13  # history, candidates, map
    text = mos.text()
    for c in ctx.candidates:  # nothing is lost: each candidate's cell and action are named
        assert f"Candidate {c.index}: [views: cell {c.index} of the candidate views]" in text
    assert "[step 10] (history tile 10)" in text
    assert prompt_tokens(mos) <= 0.40 * prompt_tokens(sep)
    assert mos.digest() != sep.digest() and mos.meta["layout"] == "mosaic"


def test_auto_layout_follows_the_image_budget_down_to_one_panel():
    ctx = synthetic_context(4, step=3)
    n_sep = PromptBuilder().separate_image_count(ctx)
    assert PromptBuilder(PromptConfig(layout="auto", max_images_per_prompt=n_sep)).build(ctx).meta["layout"] == "separate"
    p3 = PromptBuilder(PromptConfig(layout="auto", max_images_per_prompt=n_sep - 1)).build(ctx)
    assert p3.meta["layout"] == "mosaic" and len(p3.images()) == 3
    p1 = PromptBuilder(PromptConfig(layout="auto", max_images_per_prompt=1, max_image_px=1024)).build(ctx)
    assert [i.tag for i in p1.images()] == ["panel"] and max(p1.images()[0].rgb.shape[:2]) <= 1024
    assert "(panel section 2 of 3, counted from the top)" in p1.text()


# --- profiles and parsing -----------------------------------------------------------------------------

def test_profiles_are_data_and_overridable():
    assert {"openai", "azure-openai", "vllm", "sglang", "ollama", "lmstudio", "gemini-openai", "generic"} <= set(PROFILES)
    assert profile("openai").token_limit_param == "max_completion_tokens"
    assert profile("vllm").max_images_per_prompt == 1
    assert profile("vllm", {"max_images_per_prompt": 8}).max_images_per_prompt == 8
    with pytest.raises(ValueError):
        profile("nope")
    with pytest.raises(ValueError):
        profile("vllm", {"image_token_rule": "guess"})
    with pytest.raises(ValueError):
        OpenAIConfig(profile="nope", base_url="http://127.0.0.1:1/v1")
    listing = {"data": [{"id": "Qwen/Qwen2.5-VL-7B-Instruct", "max_model_len": 16384}]}
    assert context_from_models_listing(listing, "Qwen/Qwen2.5-VL-7B-Instruct") == 16384
    assert context_from_models_listing({"data": [{"id": "x", "max_model_len": -1}]}, "x") is None
    assert is_context_overflow("This model's maximum context length is 32768 tokens. However, ...")
    assert not is_context_overflow("At most 1 image(s) may be provided in one request.")


def test_think_blocks_and_prose_around_the_json():
    assert parse_answer('<think>left looks {wrong}</think>\nSo: {"action": 2, "reasoning": "r"}', [1, 2]) == (2, "r")
    assert split_thinking('I compare {a} and {b}.</think>{"action": 1}') == ('{"action": 1}', "I compare {a} and {b}.")
    assert parse_answer('Options {1, 2}; I pick {"action": 1, "reasoning": "ok"} because.', [1, 2])[0] == 1
    with pytest.raises(AnswerError, match="empty"):  # cut off while thinking: no answer at all
        parse_answer("<think>still thinking about {", [1])
    with pytest.raises(AnswerError, match="no JSON"):
        parse_answer("<think>x</think> I would go left.", [1])


# --- one mission per profile against its emulated server ---------------------------------------------

# profile -> (emulated server, its limits for this deployment, the policy's overrides)
DEPLOYMENTS = {
    "openai": ("openai", {}, {}),
    "azure-openai": ("openai", {"emulate_max_images": 50}, {}),
    "gemini-openai": ("vllm", {"emulate_max_images": 3600, "emulate_context_tokens": 1_048_576}, {}),
    "vllm": ("vllm", {}, {}),  # one image, 32k window read from /v1/models
    "sglang": ("vllm", {"emulate_max_images": 10_000}, {}),
    # A small num_ctx (the toy episode's prompts are ~3.4k tokens): the budget must compress.
    "ollama": ("ollama", {"emulate_context_tokens": 3000}, {"profile_overrides": {"context_window_tokens": 3000}}),
    "lmstudio": ("ollama", {"emulate_context_tokens": 3000}, {"profile_overrides": {"context_window_tokens": 3000}}),
    "generic": ("vllm", {"emulate_max_images": 4, "emulate_context_tokens": 16_384},
                {"max_images_per_prompt": 4}),
}


@pytest.mark.parametrize("name", sorted(DEPLOYMENTS))
def test_a_mission_runs_in_every_profile_against_its_emulated_server(name, reference):
    emulate, limits, overrides = DEPLOYMENTS[name]
    with StandinServer(StandinConfig(latency_s=0.0, emulate=emulate, **limits)) as srv, \
            POLICIES.create("openai", _cfg(srv.url, profile=name, **overrides)) as policy:
        _, stop, decisions = run_episode(_world(), policy, INSTRUCTION, max_steps=8)
    assert srv.stats.refusals == []  # nothing was sent that the server refuses
    assert not any(d.fallback for d in decisions)
    assert (stop, [d.candidate_index for d in decisions]) == reference  # same episode as the heuristic's
    limit = limits.get("emulate_max_images", {"openai": 500, "vllm": 1, "ollama": None}[emulate])
    assert limit is None or max(srv.stats.images_per_request) <= limit
    assert all(d.prompt_notes.startswith("layout ") for d in decisions)
    if name in ("ollama", "lmstudio"):  # 3000 tokens: something had to go, and the record says so
        assert any("(budget 2800)" in d.prompt_notes for d in decisions), [d.prompt_notes for d in decisions]


def test_the_old_separate_prompt_is_refused_by_vllm_and_ends_the_mission():
    """13+ separate images to a vLLM with its default --limit-mm-per-prompt: a 400 with vLLM's body,
    raised at once (no retry, no heuristic fallback) with the server's message."""
    with StandinServer(StandinConfig(latency_s=0.0, emulate="vllm")) as srv, \
            POLICIES.create("openai", _cfg(srv.url, profile="generic", layout="separate", retries=3,
                                           on_error="fallback")) as policy:
        with pytest.raises(RequestRejectedError, match=r"At most 1 image\(s\) may be provided in one request"):
            run_episode(_world(), policy, INSTRUCTION, max_steps=8)
    assert srv.stats.requests == 1 and srv.stats.by_outcome == {"refused": 1}
    assert srv.stats.refusals == ["At most 1 image(s) may be provided in one request."]


def test_a_wrong_parameter_is_a_400_that_ends_the_mission():
    # The generic profile sends max_tokens; OpenAI's reasoning models refuse it (the openai profile works).
    with StandinServer(StandinConfig(latency_s=0.0, emulate="openai")) as srv, \
            POLICIES.create("openai", _cfg(srv.url, profile="generic", on_error="fallback")) as policy:
        with pytest.raises(RequestRejectedError, match="Use 'max_completion_tokens' instead"):
            run_episode(_world(), policy, INSTRUCTION, max_steps=2)
    assert srv.stats.requests == 1


def test_a_context_overflow_answer_gets_one_compressed_retry(reference):
    """The policy believes a 400k window; the server has 2500: its overflow answer triggers exactly one
    retry with a prompt half the size, which fits."""
    with StandinServer(StandinConfig(latency_s=0.0, emulate="vllm", emulate_max_images=100,
                                     emulate_context_tokens=2500)) as srv, \
            POLICIES.create("openai", _cfg(srv.url, profile="vllm", context_window_tokens=400_000,
                                           layout="separate", profile_overrides={"max_images_per_prompt": 100})
                            ) as policy:
        _, stop, decisions = run_episode(_world(), policy, INSTRUCTION, max_steps=8)
    assert (stop, [d.candidate_index for d in decisions]) == reference
    assert srv.stats.refusals and all("maximum context length is 2500" in r for r in srv.stats.refusals)
    assert len(srv.stats.refusals) == sum("retried" in d.prompt_notes for d in decisions)  # one per step at most


def test_a_prompt_that_cannot_fit_is_never_sent():
    with StandinServer(StandinConfig(latency_s=0.0, emulate="vllm")) as srv, \
            POLICIES.create("openai", _cfg(srv.url, profile="vllm", context_window_tokens=800,
                                           on_error="fallback")) as policy:
        with pytest.raises(ContextBudgetError, match="not sent"):
            run_episode(_world(), policy, INSTRUCTION, max_steps=2)
    assert srv.stats.requests == 0


def test_replay_keys_differ_by_layout(tmp_path):
    ctx = synthetic_context(4, step=2)
    keys = set()
    for layout in ("separate", "mosaic"):
        cfg = ReplayConfig(path=str(tmp_path / "c.jsonl"), inner="openai",
                           inner_config={"layout": layout, "profile": "openai"})
        with POLICIES.create("replay", cfg) as replay:
            keys.add(replay.key(ctx))
    assert len(keys) == 2


def test_the_run_estimate_follows_the_policys_layout_and_profile():
    from types import SimpleNamespace

    from evaluation.ledger import estimate_run
    from shared.pricing import PriceTable

    eps = [SimpleNamespace(instruction="Go to the kitchen.", reference_path_m=[[0, 0, 0], [8, 0, 0]])]
    est = {layout: estimate_run(eps, model="gpt-5.1", prices=PriceTable(), max_steps=20, waypoints=6,
                                policy_config={"layout": layout})
           for layout in ("separate", "mosaic")}
    assert est["mosaic"].prompt_tokens < 0.5 * est["separate"].prompt_tokens
    assert est["mosaic"].assumptions["layout"] == "mosaic"
    qwen = estimate_run(eps, model="qwen", prices=PriceTable(), max_steps=20, policy_config={"profile": "vllm"})
    assert qwen.assumptions["image_rule"] == "qwen_patches" and qwen.cost_usd == 0.0
