"""A mission end to end under each emulated VLM server (issue 35): the real system (launcher processes:
router, robot-io, gateway, the shared services), the planner's openai policy with the matching provider
profile, the LLM stand-in emulating vLLM, Ollama or OpenAI (a real HTTP server), the runner through the
gateway. Then the old separate-image prompt against vLLM: refused with vLLM's message, which ends the
mission at once."""

from __future__ import annotations

import json

import pytest

from evaluation.cli import main
from evaluation.dataset import SetSpec, generate_set, write_set
from evaluation.results import ResultsLog
from services.planner.tools.llm_standin import StandinConfig, StandinServer
from tests.e2e.test_eval import CURATED_DENSITY_PER_M2  # sparse: the maps' density is not what is tested

pytestmark = [pytest.mark.e2e, pytest.mark.system, pytest.mark.timeout(600)]

# A small house, and one curated map for all four runs (``--maps``: the runner reuses a map the gateway
# still has): what differs between the runs is the server the planner talks to, not the map. Each run
# used to build robot-io's default house, sample and upload its curated cloud (1000 points per m2) and have
# the renderer index it: 79 s for the three runs and 24 s for the refused one, now 15 s and 1 s (CPU of
# the file, the session's system included: 95 -> 33 s).
AREA_M2 = 60.0

# emulated server -> (its limits, the policy config beyond base_url)
SERVERS = {
    "vllm": ({}, {"profile": "vllm"}),  # one image per request: the prompt becomes one panel
    "ollama": ({"emulate_context_tokens": 8192}, {"profile": "ollama",
                                                  "profile_overrides": {"context_window_tokens": 8192}}),
    "openai": ({}, {"profile": "openai"}),
}


def _run(tmp_path, launcher, episodes, maps, name: str, limits: dict, policy: dict) -> tuple[dict, StandinServer]:
    out = tmp_path / name
    with StandinServer(StandinConfig(latency_s=0.0, policy="straight", stop_after=3, emulate=name.split("-")[0],
                                     **limits)) as llm:
        cfg = {"model": "standin", "base_url": llm.url, "api_key": "test", "max_completion_tokens": 200,
               "retries": 0, **policy}
        argv = ["run", "--episodes", str(episodes), "--out", str(out), "--policy", "openai",
                "--policy-config", json.dumps(cfg), "--map-source", "curated", "--max-steps", "6",
                "--mission-timeout-s", "240", "--no-progress", "--gateway", launcher.gateway_urls[0],
                "--maps", str(maps), "--curated-density-per-m2", CURATED_DENSITY_PER_M2]
        assert main(argv) == 0
    return ResultsLog(out / "results.jsonl").load(), llm


@pytest.fixture(scope="module")
def episodes(tmp_path_factory):
    ds, gt = generate_set(SetSpec(houses=1, per_house=1, floors=(1,), seed=3, area_m2=AREA_M2), with_gt=True)
    return write_set(ds, gt, tmp_path_factory.mktemp("set") / "set.json.gz")[0]


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """The runs' shared scene -> map id index (``--maps``)."""
    return tmp_path_factory.mktemp("maps") / "maps.json"


# The session's launched system (tests/conftest.py), through robot0's gateway; the runner switches its
# robot's scene, and ``system_on_scene`` puts it back afterwards.
def test_one_mission_per_emulated_server(tmp_path, system_on_scene, episodes, maps):
    run = lambda *a: _run(tmp_path, system_on_scene, episodes, maps, *a)  # noqa: E731
    for name, (limits, policy) in SERVERS.items():
        results, llm = run(name, limits, policy)
        assert len(results) == 1, name
        (r,) = results.values()
        assert r.status == "done", (name, r.reason)
        assert llm.stats.refusals == [] and llm.stats.by_outcome.get("ok", 0) >= 1, (name, llm.stats)
        if name == "vllm":
            assert max(llm.stats.images_per_request) == 1


def test_the_old_separate_prompt_is_refused_by_vllm_and_ends_the_mission(tmp_path, system_on_scene, episodes, maps):
    results, llm = _run(tmp_path, system_on_scene, episodes, maps, "vllm-old", {},
                        {"profile": "generic", "layout": "separate"})
    (r,) = results.values()
    assert r.status != "done" and "At most 1 image(s) may be provided in one request" in r.reason, r.reason
    assert llm.stats.requests == 1 and llm.stats.by_outcome == {"refused": 1}
