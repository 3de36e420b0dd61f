"""The scene graph (issue 32): schema checks, the builder on a generated house's map, a map without labels,
the store's copy beside the cloud, and the HTTP route."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from evaluation.clouds import sample_scene_cloud
from libs.scenegraph import build_scene_graph, colour_name
from services.reconstructor.core import MapStore
from shared.cloud import PointCloud
from shared.schemas import FloorGrid, NavEdge, NavGraph, NavNode, SceneGraph, SceneObject, SceneRoom


@pytest.fixture(scope="module")
def house_cloud(house_robot, house_viewpoints) -> PointCloud:
    # The map's labelled points (visible surfaces only): what the builder may read. The scene's own rooms
    # are used below only to check the graph, never given to the builder.
    return sample_scene_cloud(house_robot.scene, density_per_m2=400, max_points=300_000,
                              viewpoints_m=house_viewpoints)


def test_schema_refuses_non_finite_out_of_range_and_dangling_references():
    room = dict(room_id="kitchen-1", room_type="kitchen", centroid_m=(1.0, 2.0, 0.0), area_m2=12.0)
    SceneGraph(rooms=[SceneRoom(**room)])
    with pytest.raises(ValidationError):
        SceneRoom(**{**room, "centroid_m": (float("nan"), 0.0, 0.0)})
    with pytest.raises(ValidationError):
        SceneRoom(**{**room, "area_m2": -1.0})
    with pytest.raises(ValidationError):
        SceneObject(object_id="bed-1", label="bed", position_m=(0, 0, 0), size_m=(1.0, -2.0, 0.5))
    with pytest.raises(ValidationError):
        SceneObject(object_id="bed-1", label="bed", position_m=(0, 0, 0), size_m=(1, 1, 1), colour_rgb=(0, 0, 300))
    with pytest.raises(ValidationError, match="unknown room"):
        SceneGraph(rooms=[SceneRoom(**room)], objects=[SceneObject(object_id="bed-1", label="bed",
                   position_m=(0, 0, 0), size_m=(1, 1, 1), room_id="bedroom-9")])
    with pytest.raises(ValidationError, match="unique"):
        SceneGraph(rooms=[SceneRoom(**room), SceneRoom(**room)])
    with pytest.raises(ValidationError):
        FloorGrid(floor=0, z_m=0.0, origin_m=(0.0, 0.0), cell_m=0.25, cells=np.full((2, 2), 7, np.uint8))
    with pytest.raises(ValidationError):
        FloorGrid(floor=0, z_m=0.0, origin_m=(0.0, 0.0), cell_m=0.0, cells=np.zeros((2, 2), np.uint8))


def test_builder_finds_every_room_instance_and_the_objects_in_them(house_robot, house_cloud):
    g = build_scene_graph(house_cloud)
    truth = house_robot.scene  # ground truth, only to check the graph built from the points
    assert g.labelled and g.floors_z_m == [0.0]
    want = [r.room_type for r in truth.rooms if r.room_type != "staircase"]
    got = [r.room_type for r in g.rooms]
    assert set(got) == set(want)
    # Two offices are two nodes. Known miss: two bedrooms joined by a wide opening stay one room.
    assert got.count("office") == want.count("office") == 3 and got.count("bathroom") == 2
    assert len(got) >= len(want) - 1
    for r in g.rooms:
        here = truth.room_at(np.array(r.centroid_m))
        assert here is not None and here.room_type == r.room_type, (r.room_id, here)
        assert r.neighbours, f"{r.room_id} opens onto no room"
    assert {o.a for o in g.openings} | {o.b for o in g.openings} == {r.room_id for r in g.rooms}
    beds = [o for o in g.objects if o.label == "bed"]
    assert len(beds) >= sum(1 for o in truth.objects if o.label == "bed")
    for b in beds[:3]:
        assert g.room(b.room_id).room_type in ("bedroom", "bathroom", "hallway")
    big = [o for o in g.objects if o.points >= 500]
    in_right_room = sum(1 for o in big if truth.room_at(np.array(o.position_m)) is not None
                        and truth.room_at(np.array(o.position_m)).room_type == g.room(o.room_id).room_type)
    assert in_right_room >= 0.8 * len(big)
    walk = g.free_space[0].cells
    assert 0.3 < (walk > 0).sum() * 0.25**2 / sum(r.area_m2 for r in g.rooms) <= 1.2


def test_a_map_without_labels_gets_a_geometric_graph_from_the_regions(house_cloud):
    bare = PointCloud(house_cloud.xyz, house_cloud.rgb)
    xs = np.arange(1.0, 15.0, 1.0)
    nodes = [NavNode(node_id=f"n{i}", position_m=(float(x), 3.0, 0.0), visited=True, region=int(x > 8))
             for i, x in enumerate(xs)]
    edges = [NavEdge(a=f"n{i}", b=f"n{i + 1}", length_m=1.0) for i in range(len(xs) - 1)]
    g = build_scene_graph(bare, NavGraph(nodes=nodes, edges=edges))
    assert not g.labelled and not g.objects
    assert g.rooms and all(r.room_type == "" for r in g.rooms)
    assert {r.region for r in g.rooms} == {0, 1}
    assert any(r.neighbours for r in g.rooms)
    assert len(g.navigation.nodes) == len(nodes)


def test_colour_names_survive_shading():
    assert colour_name(np.array([200, 41, 36])) == "red"
    assert colour_name(np.array([100, 20, 18])) == "red"  # the same red in shadow
    assert colour_name(np.array([46, 82, 200])) == "blue"


def test_store_keeps_the_graph_beside_every_version(tmp_path, house_cloud):
    store = MapStore(tmp_path, fsync=False)
    nav = NavGraph(nodes=[NavNode(node_id="a", position_m=(1.0, 1.0, 0.0), visited=True, region=0)], edges=[])
    v1 = store.save("house", house_cloud, navigation=nav)
    v2 = store.save("house", PointCloud(house_cloud.xyz, house_cloud.rgb))
    g1, g2 = store.scene_graph("house", v1.version), store.scene_graph("house")
    assert (g1.version, g2.version) == (1, 2) and g1.map_id == "house"
    assert g1.labelled and not g2.labelled and g1.navigation.nodes[0].node_id == "a"
    assert (tmp_path / "house" / "v000001" / "scene_graph.json").is_file()
    again = SceneGraph.model_validate_json(g1.model_dump_json())
    assert [r.room_id for r in again.rooms] == [r.room_id for r in g1.rooms]
    assert np.array_equal(again.free_space[0].cells, g1.free_space[0].cells)
    (tmp_path / "house" / "v000001" / "scene_graph.json").write_text("{}")
    with pytest.raises(Exception, match="checksum"):
        store.scene_graph("house", 1)
