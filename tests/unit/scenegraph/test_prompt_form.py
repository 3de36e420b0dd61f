"""The scene graph's text form in the MLLM prompt (issue 32): names, neighbours, the agent's room, the size
bound, the off switch, and the prompt that really reaches an OpenAI-compatible server (the stand-in)."""

from __future__ import annotations

import numpy as np
import pytest

from libs.scenegraph import build_scene_graph
from libs.scenegraph.text import room_names, scene_graph_text
from services.planner.core import POLICIES, OpenAIConfig
from services.planner.core.context import StepContext, build_candidate_views
from services.planner.core.prompt import PromptBuilder, PromptConfig
from services.planner.tools.llm_standin import StandinConfig, StandinServer
from shared.schemas import Candidate, CandidateKind, Pose, SceneGraph, SceneObject, SceneOpening, SceneRoom
from tests.unit.scenegraph.test_graph_policy import _two_rooms

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def graph():
    return build_scene_graph(_two_rooms())


def _ctx(graph, at=(1.0, 2.0, 0.0)) -> StepContext:
    cands = [Candidate(index=0, dx_m=1.0, dy_m=0.0, angle_rad=0.0, distance_m=1.0),
             Candidate(index=1, kind=CandidateKind.STOP)]
    views = build_candidate_views(cands, None)
    for v in views:
        v.observed_rgb = np.zeros((64, 64, 3), np.uint8)
    return StepContext(instruction="Go into the bedroom and stop next to the blue bed.", step=0,
                       pose=Pose(position_m=at), candidates=views, scene_graph=graph)


def test_text_names_rooms_their_neighbours_objects_and_where_the_agent_is(graph):
    text = scene_graph_text(graph, (1.0, 2.0, 0.0))
    assert "You are in the kitchen, on floor 0" in text
    lines = {ln.split(" | ")[0]: ln for ln in text.splitlines() if ln.startswith("- ")}
    assert set(lines) == {"- kitchen (you are here)", "- bedroom"}
    assert lines["- bedroom"].endswith("| kitchen") and lines["- kitchen (you are here)"].endswith("| bedroom")
    assert "red bed" in lines["- bedroom"] and "blue bed" in lines["- bedroom"]
    assert "no objects seen" in lines["- kitchen (you are here)"]
    # From the bedroom the agent's room moves and is listed first.
    text = scene_graph_text(graph, (7.0, 2.0, 0.0))
    assert "You are in the bedroom" in text
    assert text.index("- bedroom (you are here)") < text.index("- kitchen")
    assert "You are" not in scene_graph_text(graph)


def _big_house(n: int) -> SceneGraph:
    """A corridor of ``n`` numbered bedrooms, each with a lamp: far beyond any prompt budget."""
    rooms = [SceneRoom(room_id=f"r{k}", room_type="bedroom", centroid_m=(4.0 * k, 0.0, 0.0), area_m2=16.0,
                       neighbours=[f"r{j}" for j in (k - 1, k + 1) if 0 <= j < n]) for k in range(n)]
    openings = [SceneOpening(a=f"r{k}", b=f"r{k + 1}", position_m=(4.0 * k + 2.0, 0.0, 0.0)) for k in range(n - 1)]
    objects = [SceneObject(object_id=f"o{k}", label="lamp", colour="white", position_m=(4.0 * k, 1.0, 0.5),
                           size_m=(0.3, 0.3, 0.5), room_id=f"r{k}") for k in range(n)]
    return SceneGraph(labelled=True, floors_z_m=[0.0], rooms=rooms, openings=openings, objects=objects)


def test_a_big_house_is_cut_to_the_rooms_nearest_the_agent_and_says_so():
    g = _big_house(300)
    names = room_names(g)
    assert names["r0"] == "bedroom 1" and names["r299"] == "bedroom 300"  # same-type rooms numbered
    text = scene_graph_text(g, (4.0 * 150, 0.0, 0.0), max_chars=1500)
    assert len(text) <= 1500
    listed = [ln for ln in text.splitlines() if ln.startswith("- ")]
    assert 5 <= len(listed) < 300
    assert listed[0].startswith("- bedroom 151 (you are here)")
    # The nearest rooms by hops through openings: 150 and 152 come next, both one door away.
    assert {ln.split(" | ")[0] for ln in listed[1:3]} == {"- bedroom 150", "- bedroom 152"}
    assert f"(... {300 - len(listed)} more rooms, farther from you, left out: the map is large)" in text


def test_geometric_graph_has_numbered_unnamed_rooms():
    g = SceneGraph(rooms=[SceneRoom(room_id="a", centroid_m=(0, 0, 0), area_m2=10, neighbours=["b"]),
                          SceneRoom(room_id="b", centroid_m=(5, 0, 0), area_m2=10, neighbours=["a"])])
    text = scene_graph_text(g, (5.0, 0.0, 0.0))
    assert "rooms are unnamed" in text and "- room 2 (you are here)" in text and "You are in room 2" in text


def test_the_prompt_carries_the_block_and_the_switch_removes_it(graph):
    on = PromptBuilder().build(_ctx(graph))
    off = PromptBuilder(PromptConfig(scene_graph=False)).build(_ctx(graph))
    assert "You are in the kitchen" in on.text() and on.meta["scene_graph"] is True
    assert "scene graph" not in off.text() and "You are in" not in off.text() and off.meta["scene_graph"] is False
    # The block sits between the instruction and the history, and nothing else changes.
    assert on.text().index("Instruction:") < on.text().index("Map of the building") < on.text().index("History")
    assert on.text().replace(scene_graph_text(graph, (1.0, 2.0, 0.0)) + "\n\n", "") == off.text()
    # No graph for the mission: no block (and the same prompt as switched off).
    ctx = _ctx(graph)
    ctx.scene_graph = None
    assert PromptBuilder().build(ctx).text() == off.text()


@pytest.mark.parametrize("switch", [True, False])
def test_the_prompt_the_llm_receives_contains_the_graph_and_its_tokens_are_counted(graph, switch):
    with StandinServer(StandinConfig(latency_s=0.0)) as srv, POLICIES.create(
            "openai", OpenAIConfig(model="gpt-4o-mini", base_url=srv.url, api_key="test", timeout_s=5.0,
                                   retries=0, on_error="raise", scene_graph=switch)) as policy:
        decision = policy.decide(_ctx(graph))
        sent = list(srv.prompts)
        tokens = srv.stats.prompt_tokens
    assert len(sent) == 1 and not decision.fallback
    assert ("You are in the kitchen" in sent[0] and "- bedroom | floor 0" in sent[0]) is switch
    assert ("Map of the building" in sent[0]) is switch
    # The ledger's tokens are the server's count of what was sent, graph included.
    assert decision.prompt_tokens == tokens == policy.usage.prompt_tokens > 0


def test_the_mllm_preset_switches_the_graph_and_exists_only_with_an_llm(monkeypatch):
    from evaluation.presets import presets
    from evaluation.runner import RunConfig

    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    monkeypatch.delenv("ANT_OPENAI_BASE_URL", raising=False)
    assert "scene-graph-mllm" not in presets()  # "all" never starts a paid run by surprise
    monkeypatch.setenv("ANT_OPENAI_BASE_URL", "http://127.0.0.1:1/v1")
    variants = presets()["scene-graph-mllm"].variants
    assert [(v.overrides["policy"], v.overrides["policy_config"]["scene_graph"]) for v in variants] == \
        [("openai", False), ("openai", True)]
    for v in variants:  # the overrides are a valid run config and a valid openai policy config
        cfg = RunConfig.model_validate({**RunConfig().model_dump(), **v.overrides})
        assert OpenAIConfig(**cfg.policy_config).scene_graph is v.overrides["policy_config"]["scene_graph"]
