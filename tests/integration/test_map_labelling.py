"""The MLLM labeller wired into the map store (issue 32): a map build through the reconstructor core
(build job -> reconstruction of RGB-D tours -> store) names its scene graph's rooms by asking a real
OpenAI-compatible HTTP server (the stand-in, on 127.0.0.1) once per region with a few of that region's
tour frames; the answers are cached beside the map, the usage is in the map's info.

The tours are ray-cast from a two-room mesh (a red room x 0-4, a green one x 4.2-8, a door between):
the stand-in names a red room a kitchen and a green one a bedroom from the pixels it is sent."""

from __future__ import annotations

import threading

import numpy as np
from shared.o3d import o3d
import pytest

from libs.scenegraph.labeller import LABELLERS
from services.planner.tools.llm_standin import StandinConfig, StandinServer
from services.reconstructor.core import MapStore, ReconstructionConfig
from services.reconstructor.core.build_job import LABELLER_FRAMES, build_map, labeller_frames
from services.reconstructor.service import FrameBuffer, ReconstructorSettings
from shared import keys
from shared.bus.typed import TypedBus
from shared.events import EventStream
from shared.jobs import JobContext
from shared.schemas import (
    BuildMapRequest, CameraIntrinsics, Frame, JobState, NavEdge, NavGraph, NavNode, Pose, TourRecording,
)
from tests.raycast import box_scene, cast_view

pytestmark = pytest.mark.timeout(120)

CAM = CameraIntrinsics(width_px=48, height_px=36, hfov_deg=90.0)
COLOURS = {0: (200, 40, 40), 1: (40, 190, 60)}  # region -> wall and floor colour
CENTRES = {0: (2.0, 2.0), 1: (6.0, 2.0)}
N_FRAMES = 9  # per region: more than the build keeps for the labeller (LABELLER_FRAMES)


def _scene() -> o3d.t.geometry.RaycastingScene:
    return box_scene([((0, 0, -0.1), (8, 4, 0)), ((0, 0, 2.5), (8, 4, 2.6)),  # floor, ceiling
                      ((-0.1, 0, 0), (0, 4, 2.5)), ((8, 0, 0), (8.1, 4, 2.5)),  # end walls
                      ((0, -0.1, 0), (8, 0, 2.5)), ((0, 4, 0), (8, 4.1, 2.5)),  # side walls
                      ((4.0, 0, 0), (4.2, 1.5, 2.5)), ((4.0, 2.5, 0), (4.2, 4, 2.5))])  # the wall with its door


def _frame(scene, index: int, region: int, heading: float) -> Frame:
    cx, cy = CENTRES[region]
    pos = (cx + 0.3 * np.cos(heading), cy + 0.3 * np.sin(heading), 0.0)
    depth, hits = cast_view(scene, CAM, pos, heading)
    rgb = np.where((hits[..., 0] < 4.1)[..., None], COLOURS[0], COLOURS[1]).astype(np.uint8)
    return Frame(index=index, timestamp_s=float(index), pose=Pose(position_m=pos, heading_rad=heading),
                 imu_heading_rad=heading, camera=CAM, rgb=rgb, depth_m=depth)


def _nav() -> NavGraph:
    spots = [(1.5, 1.5), (2.5, 2.5), (3.2, 2.0), (5.0, 2.0), (6.0, 2.5), (7.0, 1.5)]
    nodes = [NavNode(node_id=f"n{i}", position_m=(x, y, 0.0), visited=True, region=int(x > 4.1))
             for i, (x, y) in enumerate(spots)]
    return NavGraph(nodes=nodes, edges=[NavEdge(a=f"n{i}", b=f"n{i + 1}", length_m=1.0) for i in range(5)])


@pytest.fixture(scope="module")
def tours():
    scene = _scene()
    return {r: [_frame(scene, i, r, 2 * np.pi * i / N_FRAMES) for i in range(N_FRAMES)] for r in (0, 1)}


@pytest.fixture
def bus(peers):
    """Where the build's progress events go: a real zenoh peer (the events are not under test here; the
    stored map and its info are)."""
    return TypedBus(peers[0], "reconstructor")


def _build(store: MapStore, tours, build_id: str, bus: TypedBus):
    frames = FrameBuffer(64 << 20)
    recordings = []
    for region, got in tours.items():
        name = f"{build_id}-r{region}"
        for f in got:
            frames.add(name, f)
        recordings.append(TourRecording(exploration_id="e1", recording=name, region=region,
                                        start_pose=got[0].pose, frame_count=len(got)))
    req = BuildMapRequest(build_id=build_id, exploration_id="e1", map_id="house", recordings=recordings,
                          reconstruction="rgbd", navigation=_nav())
    events = keys.MAP_BUILD_EVENTS.format(map="house", build=build_id)
    ctx = JobContext(build_id, threading.Event(), EventStream(bus, events, build_id))
    end = build_map(ctx, req, frames=frames, store=store, config=ReconstructionConfig(backend="rgbd"),
                    announce=lambda info: None, frames_timeout_s=1.0)
    assert end.state == JobState.SUCCEEDED
    return end.payload.info


def _mllm(url: str, **kw):
    return LABELLERS.create("mllm", {"model": "gpt-4o-mini", "base_url": url, "api_key": "test", "timeout_s": 10.0,
                                     "frames_per_region": 3, **kw})


def test_a_build_with_the_mllm_labeller_names_its_rooms_once_and_counts_the_cost(tmp_path, tours, bus):
    with StandinServer(StandinConfig(latency_s=0.0)) as srv:
        store = MapStore(tmp_path / "maps", fsync=False, labeller=_mllm(srv.url))
        info = _build(store, tours, "b1", bus)
        calls_first = srv.stats.requests
        # The store restarts (a new process reads the same folder) and the same tours are built again.
        again = _build(MapStore(tmp_path / "maps", fsync=False, labeller=_mllm(srv.url)), tours, "b2", bus)
        calls_after = srv.stats.requests
        sent = list(srv.prompts)
    graph = store.scene_graph("house", info.version)
    named = {r.region: r.room_type for r in graph.rooms}
    assert named == {0: "kitchen", 1: "bedroom"} and graph.labelled
    # One call per region with frames_per_region frames (of the LABELLER_FRAMES the build kept).
    assert calls_first == 2 and [s.count("<image>") for s in sent] == [3, 3]
    lab = info.labelling
    assert lab.labeller == "mllm" and lab.model == "gpt-4o-mini" and lab.error == ""
    assert lab.regions == 2 and lab.rooms_named == 2 and lab.calls == 2 and lab.prompt_tokens > 0
    assert lab.cost_usd > 0 and lab.cache_hits == 0
    # The second build of the same frames: a new version, the same names, no call.
    assert again.version == info.version + 1 and calls_after == calls_first
    assert again.labelling.calls == 0 and again.labelling.cache_hits == 2 and again.labelling.cost_usd == 0
    assert {r.region: r.room_type for r in store.scene_graph("house", again.version).rooms} == named
    # The info read back from the store says the same (it is the map's metadata, not only the reply).
    assert store.info("house", info.version).labelling == lab


@pytest.mark.parametrize("fault", ["500", "garbled"])
def test_a_refused_or_garbled_answer_leaves_the_geometric_graph_and_says_so(tmp_path, tours, fault, bus):
    # Refused: the server answers HTTP 500. Garbled: the answer is no JSON, twice (the labeller's
    # corrective re-ask included) - the stand-in's Ollama emulation cuts an over-long prompt from the
    # start (its system message with it), as Ollama does, and answers without JSON.
    cfg = (StandinConfig(latency_s=0.0, fault_script=["500"]) if fault == "500" else
           StandinConfig(latency_s=0.0, emulate="ollama", emulate_context_tokens=256))
    with StandinServer(cfg) as srv:
        store = MapStore(tmp_path / "maps", fsync=False, labeller=_mllm(srv.url))
        info = _build(store, tours, "b1", bus)
    graph = store.scene_graph("house", info.version)
    assert sorted(r.region for r in graph.rooms) == [0, 1]
    assert [r.room_type for r in graph.rooms] == ["", ""] and not graph.labelled
    lab = info.labelling
    assert lab.labeller == "mllm" and lab.rooms_named == 0 and lab.error
    assert ("HTTP 500" in lab.error) if fault == "500" else ("JSON" in lab.error)
    # What was asked before the failure is billed all the same.
    assert lab.calls == (0 if fault == "500" else 2) and (lab.prompt_tokens > 0) == (fault != "500")


def test_the_labeller_is_a_setting_of_the_reconstructor():
    assert ReconstructorSettings().labeller == "sim"
    s = ReconstructorSettings(_cli_parse_args=["--labeller", "mllm", "--labeller_config",
                                               '{"model": "gpt-4o-mini", "base_url": "http://127.0.0.1:9/v1"}'])
    assert (s.labeller, s.labeller_config["model"]) == ("mllm", "gpt-4o-mini")
    with pytest.raises(Exception, match="unknown scene-graph labeller"):
        ReconstructorSettings(labeller="detector")
    with pytest.raises(Exception, match="base_url"):
        ReconstructorSettings(labeller="mllm", labeller_config={"base_url": "ftp://x"})
    assert LABELLER_FRAMES >= 3


def test_the_build_keeps_a_bounded_number_of_downscaled_frames_per_region():
    """A region's tour of 50 VGA frames costs the labeller 8 frames of at most 384 px, spread over the tour."""
    tour = [np.full((480, 640, 3), i, np.uint8) for i in range(50)]
    kept = labeller_frames(tour)
    assert len(kept) == LABELLER_FRAMES and all(f.shape == (288, 384, 3) and f.dtype == np.uint8 for f in kept)
    assert [int(f[0, 0, 0]) for f in kept][::7] == [0, 49]  # the first and the last frame of the tour
    assert len(labeller_frames(tour[:3])) == 3
