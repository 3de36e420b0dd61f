"""The scene graph in the Rerun recording (issue 32), read back with rerun's own reader: room names at the
centroids, footprints, objects with labels, openings, the navigation graph as line strips, stairs."""

from __future__ import annotations

import numpy as np
import rerun as rr

from libs.scenegraph import build_scene_graph
from shared.recording import RecordingInput, entity_rows, write_recording
from shared.scene_names import room_names
from shared.schemas import NavEdge, NavGraph, NavNode, SceneStairs
from tests.unit.scenegraph.test_graph_policy import _two_rooms


def _columns(path) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for chunk in rr.chunk.RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        out.setdefault(chunk.entity_path.lstrip("/"), {}).update(
            {name: batch.column(name)[0].as_py() for name in batch.column_names if ":" in name} | {"static": chunk.is_static})
    return out


def test_recording_draws_the_scene_graph(tmp_path):
    cloud = _two_rooms()
    nav = NavGraph(nodes=[NavNode(node_id="n0", position_m=(1.0, 2.0, 0.0), visited=True),
                          NavNode(node_id="n1", position_m=(4.1, 2.0, 0.0), visited=True),
                          NavNode(node_id="n2", position_m=(7.0, 2.0, 0.0), visited=False)],
                   edges=[NavEdge(a="n0", b="n1", length_m=3.1), NavEdge(a="n1", b="n2", length_m=2.9)])
    graph = build_scene_graph(cloud, nav).model_copy(update={"stairs": [SceneStairs(
        stairs_id="s0", from_floor=0, to_floor=1, bottom_m=(0.5, 0.5, 0.0), top_m=(0.5, 3.0, 2.8))]})
    path = write_recording(RecordingInput("m-1", "mission", [], cloud.xyz, cloud.rgb, "two-rooms", scene_graph=graph),
                           tmp_path / "m-1.rrd")
    cols = _columns(path)
    names = room_names(graph)
    rooms = cols["world/scene_graph/rooms"]
    assert rooms["static"] and sorted(rooms["Points3D:labels"]) == sorted(names.values()) == ["bedroom", "kitchen"]
    # Each name sits at its room's centroid (a little above the floor).
    for label, p in zip(rooms["Points3D:labels"], rooms["Points3D:positions"]):
        room = next(r for r in graph.rooms if names[r.room_id] == label)
        assert np.allclose(p[:2], room.centroid_m[:2], atol=1e-4) and 0.0 < p[2] - room.floor_z_m < 1.0
    objects = cols["world/scene_graph/objects"]
    assert sorted(objects["Points3D:labels"]) == ["blue bed", "red bed"]
    assert len(objects["Points3D:positions"]) == len(graph.objects) == 2
    assert cols["world/scene_graph/openings"]["Points3D:labels"] == ["kitchen - bedroom"] or \
        cols["world/scene_graph/openings"]["Points3D:labels"] == ["bedroom - kitchen"]
    strips = cols["world/scene_graph/navigation"]["LineStrips3D:strips"]
    assert np.allclose(np.array(strips, float), [[(1.0, 2.0, 0.0), (4.1, 2.0, 0.0)],
                                                 [(4.1, 2.0, 0.0), (7.0, 2.0, 0.0)]], atol=1e-5)
    assert len(cols["world/scene_graph/navigation/nodes"]["Points3D:positions"]) == 3
    assert len(cols["world/scene_graph/footprints"]["LineStrips3D:strips"]) == 2
    assert cols["world/scene_graph/stairs"]["LineStrips3D:labels"] == ["stairs 0-1"]


def test_a_recording_without_a_graph_has_no_graph_entities(tmp_path):
    path = write_recording(RecordingInput("m-2", "mission", [], np.zeros((10, 3), np.float32)), tmp_path / "m-2.rrd")
    assert not any(e.startswith("world/scene_graph") for e in entity_rows(path))


# The gateway's recorder on the scripted services (a fake bus), as tests/unit/export/test_downloads.py runs it.
from tests.unit.export.test_downloads import gateway, net, rrd_contents, run_mission  # noqa: E402,F401


def test_the_gateways_recording_of_a_mission_holds_its_maps_scene_graph(gateway, tmp_path):
    with gateway() as (client, settings):
        mid = run_mission(client, record=True)
        r = client.get(f"/missions/{mid}/recording.rrd")
        assert r.status_code == 200
        expected = client.get("/maps/house/scene-graph.json").json()
    (tmp_path / "m.rrd").write_bytes(r.content)
    c = rrd_contents(tmp_path / "m.rrd")
    assert expected["rooms"], "the scripted map should give at least one room"
    rooms = c["world/scene_graph/rooms"]
    assert rooms["static"] and rooms["rows"] == 1
    assert len(rooms["batches"][0].column("Points3D:positions")[0]) == len(expected["rooms"])
