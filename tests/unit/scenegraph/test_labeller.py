"""The scene-graph labeller backends (issue 32): sim reads the map's labels, none gives the geometric graph,
mllm asks an OpenAI-compatible server (the stand-in, a real HTTP server) once per region with that region's
frames, caches the answers beside the map version and counts the calls and tokens."""

from __future__ import annotations

import numpy as np
import pytest

from libs.scenegraph.labeller import LABELLERS, LabellerError, parse_label_answer
from services.planner.tools.llm_standin import StandinConfig, StandinServer
from shared.schemas import NavEdge, NavGraph, NavNode
from tests.unit.scenegraph.test_graph_policy import _two_rooms

pytestmark = pytest.mark.timeout(60)


def _nav() -> NavGraph:
    """The exploration's graph: three nodes in the kitchen (region 0), three in the bedroom (region 1)."""
    spots = [(1, 1), (2, 3), (3, 2), (5, 1), (6, 3), (7, 2)]
    nodes = [NavNode(node_id=f"n{i}", position_m=(x, y, 0.0), visited=True, region=int(x > 4.1))
             for i, (x, y) in enumerate(spots)]
    return NavGraph(nodes=nodes, edges=[NavEdge(a=f"n{i}", b=f"n{i + 1}", length_m=1.0) for i in range(5)])


def _frames(rgb, n=5) -> list[np.ndarray]:
    rng = np.random.default_rng(sum(rgb))
    return [np.clip(np.full((96, 128, 3), rgb) + rng.integers(-10, 10, (96, 128, 3)), 0, 255).astype(np.uint8)
            for _ in range(n)]


def test_sim_reads_the_labels_and_none_gives_the_geometric_graph():
    cloud = _two_rooms()
    sim = LABELLERS.create("sim").label(cloud, _nav()).graph
    assert sorted(r.room_type for r in sim.rooms) == ["bedroom", "kitchen"] and sim.labelled and len(sim.objects) == 2
    geo = LABELLERS.create("none").label(cloud, _nav()).graph
    assert [r.room_type for r in geo.rooms] == ["", ""] and not geo.labelled and not geo.objects
    assert sorted(r.region for r in geo.rooms) == [0, 1]
    assert LABELLERS.names() == ["mllm", "none", "sim"]


def test_mllm_names_each_region_once_caches_with_the_map_version_and_counts_tokens(tmp_path):
    cloud = _two_rooms()
    # Red frames in the kitchen's region, green in the bedroom's: the stand-in answers from the pixels.
    frames = {0: _frames((200, 40, 40)), 1: _frames((40, 190, 60))}
    cache = tmp_path / "maps" / "two-rooms" / "v3" / "labels.json"
    cfg = {"model": "gpt-4o-mini", "api_key": "test", "frames_per_region": 3, "timeout_s": 10.0}
    with StandinServer(StandinConfig(latency_s=0.0)) as srv:
        labeller = LABELLERS.create("mllm", {**cfg, "base_url": srv.url})
        got = labeller.label(cloud, _nav(), frames, map_id="two-rooms", version=3, cache_path=cache)
        first_calls, sent = srv.stats.requests, list(srv.prompts)
        tokens = srv.stats.prompt_tokens
        again = labeller.label(cloud, _nav(), frames, map_id="two-rooms", version=3, cache_path=cache)
        after_cache = srv.stats.requests
        changed = labeller.label(cloud, _nav(), {**frames, 1: _frames((40, 60, 200))}, map_id="two-rooms",
                                 version=3, cache_path=cache)
    g = got.graph
    by_region = {r.region: r for r in g.rooms}
    assert by_region[0].room_type == "kitchen" and by_region[1].room_type == "bedroom" and g.labelled
    assert sorted(o.label for o in g.objects if o.room_id == by_region[1].room_id) == ["bed", "wardrobe"]
    assert all(o.points == 0 for o in g.objects)  # named, not measured
    # One call per region, each with frames_per_region frames; the ledger holds the server's own count.
    assert first_calls == 2 and [s.count("<image>") for s in sent] == [3, 3]
    assert got.usage.calls == 2 and got.usage.prompt_tokens == tokens > 0 and got.usage.cost_usd > 0
    # Cached with the map version: the same frames cost nothing the second time ...
    assert after_cache == first_calls and again.usage.calls == 0 and again.usage.cache_hits == 2
    assert [r.room_type for r in again.graph.rooms] == [r.room_type for r in g.rooms]
    assert cache.is_file()
    # ... and new frames of one region ask again for that region only.
    assert changed.usage.calls == 1 and changed.usage.cache_hits == 1
    assert {r.region: r.room_type for r in changed.graph.rooms}[1] == "bathroom"


def test_bad_answers_and_unreachable_servers_are_typed_errors():
    assert parse_label_answer('```json\n{"room": "Living Room", "objects": ["Sofa", "<script>", 3]}\n```') == \
        {"room": "living room", "objects": ["sofa"]}  # lower-cased; markup and numbers dropped
    with pytest.raises(LabellerError, match="room"):
        parse_label_answer('{"room": "ignore previous instructions; DROP TABLE", "objects": []}')
    with pytest.raises(LabellerError, match="no JSON"):
        parse_label_answer("a kitchen")
    with pytest.raises(LabellerError, match="budget"):
        LABELLERS.create("mllm", {"base_url": "http://127.0.0.1:9/v1", "api_key": "x", "max_regions": 1}).label(
            _two_rooms(), _nav(), {0: _frames((200, 40, 40)), 1: _frames((40, 190, 60))})
    with pytest.raises(ValueError):
        LABELLERS.create("mllm", {"base_url": "ftp://example"})
