"""Procedural houses: determinism, rooms, objects, labels, connectivity."""

from __future__ import annotations

import numpy as np
import pytest

from libs.world.errors import SceneFormatError
from libs.world.house import HouseSpec, generate_house

ROOM_TYPES = {"bedroom", "kitchen", "bathroom", "living room", "hallway", "office", "dining room"}


def test_generator_is_deterministic_and_seed_dependent():
    a, b, c = generate_house("generated:5"), generate_house("generated:5"), generate_house("generated:6")
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangle_labels, b.triangle_labels)
    assert [o.description for o in a.objects] == [o.description for o in b.objects]
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


@pytest.mark.parametrize("spec", ["generated:0", "generated:3", "generated:1:floors=2"])
def test_house_has_labelled_rooms_objects_and_floor_labels(spec):
    s = generate_house(spec)
    types = {r.room_type for r in s.rooms} & ROOM_TYPES
    assert len(types) >= 4
    assert len(s.objects) >= 15
    assert len({o.label for o in s.objects}) >= 8
    names = set(s.label_names.values())
    assert {"wall", "door frame", "ceiling"} <= names
    for t in types:
        assert f"{t} floor" in names
    # Every label id used by a triangle is named.
    assert set(np.unique(s.triangle_labels)) <= set(s.label_names)
    area = sum(r.area_m2 for r in s.rooms if r.room_type != "staircase")
    assert 150 <= area <= 250


def test_spec_parsing():
    assert HouseSpec.parse("generated:4:floors=2:area=150") == HouseSpec(4, 2, 150.0)
    with pytest.raises(SceneFormatError):
        HouseSpec.parse("generated:x")
    with pytest.raises(SceneFormatError):
        HouseSpec.parse("generated:1:floors=4")
    with pytest.raises(SceneFormatError):
        HouseSpec.parse("generated:1:area=1500")
    assert HouseSpec.parse("generated:1:floors=3:area=1200") == HouseSpec(1, 3, 1200.0)


def _room_floor_nodes(nav, room):
    n = nav.nodes_m
    inside = (
        (n[:, 0] > room.min_xy_m[0]) & (n[:, 0] < room.max_xy_m[0])
        & (n[:, 1] > room.min_xy_m[1]) & (n[:, 1] < room.max_xy_m[1])
        & (np.abs(n[:, 2] - room.floor_z_m) < 0.05)
    )
    return np.flatnonzero(inside)


@pytest.mark.parametrize("fixture", ["house_robot", "two_floor_robot"])
def test_house_floor_is_one_connected_region(fixture, request):
    robot = request.getfixturevalue(fixture)
    nav = robot.nav
    floor_nodes = np.concatenate([_room_floor_nodes(nav, r) for r in robot.scene.rooms if r.room_type != "staircase"])
    # Free cells inside a piece of furniture's bounding box (between a toilet's bowl and its tank)
    # are not floor anyone can walk to; every other floor cell must be in the start's region.
    xy = nav.nodes_m[floor_nodes, :2]
    inside_furniture = np.zeros(len(floor_nodes), dtype=bool)
    for o in robot.scene.objects:
        half = np.array(o.size_m[:2]) / 2 + 0.15
        inside_furniture |= np.all(np.abs(xy - np.array(o.position_m[:2])) <= half, axis=1)
    assert inside_furniture.mean() < 0.5
    comp = nav.component[floor_nodes[~inside_furniture]]
    assert np.all(comp == nav.main_component), f"{np.mean(comp != nav.main_component):.3%} of floor cells cut off"
    for r in robot.scene.rooms:
        if r.room_type != "staircase":
            assert len(_room_floor_nodes(nav, r)) > 50, r.name


def test_two_floors_joined_by_stairs(two_floor_robot):
    nav = two_floor_robot.nav
    main = nav.nodes_m[nav.component == nav.main_component]
    assert main[:, 2].min() < 0.05 and main[:, 2].max() > 2.7
    lower = two_floor_robot.scene.start_pose.xyz
    upper_room = next(r for r in two_floor_robot.scene.rooms if r.floor == 1 and r.room_type != "staircase")
    goal = nav.nodes_m[_room_floor_nodes(nav, upper_room)[0]]
    path = nav.shortest_path(lower, goal)
    assert path is not None
    d = nav.geodesic_distance(lower, goal)
    assert d > np.linalg.norm(goal - lower)  # goes round by the stairs
    assert np.max(np.abs(np.diff(nav.shortest_path(lower, goal, smooth=False)[:, 2]))) <= 0.2 + 1e-6


def test_export_ply_roundtrip(tmp_path):
    from shared.o3d import o3d

    s = generate_house("generated:2:area=80")
    path = s.export_ply(tmp_path / "house.ply")
    m = o3d.io.read_triangle_mesh(str(path))
    assert len(m.triangles) == len(s.triangles)
    assert np.allclose(np.asarray(m.vertex_colors), s.vertex_colors, atol=1 / 255)


def test_room_names_are_numbered_per_type_only_when_repeated():
    for spec in ("generated:0", "generated:1:floors=2"):
        rooms = [r for r in generate_house(spec).rooms if r.room_type != "staircase"]
        names = [r.name for r in rooms]
        assert len(set(names)) == len(names)
        for t in {r.room_type for r in rooms}:
            same = [r.name for r in rooms if r.room_type == t]
            # "bedroom", "bedroom 2", "bedroom 3": the first has no number, the others count up per type.
            assert same == [t] + [f"{t} {k}" for k in range(2, len(same) + 1)], same


@pytest.mark.parametrize("fixture", ["house_robot", "two_floor_robot"])
def test_furniture_tops_are_not_walkable(fixture, request):
    robot = request.getfixturevalue(fixture)
    nav = robot.nav
    assert nav.n_components == 1
    # Every walkable cell is floor or stairs: at a storey's floor height, or inside the stairwell.
    floors = np.array(sorted({r.floor_z_m for r in robot.scene.rooms}))
    on_floor = np.min(np.abs(nav.nodes_m[:, 2:3] - floors[None, :]), axis=1) < 0.05
    stairs = [r for r in robot.scene.rooms if r.room_type == "staircase"]
    in_stairwell = np.zeros(len(nav.nodes_m), dtype=bool)
    for r in stairs:
        in_stairwell |= np.all((nav.nodes_m[:, :2] >= r.min_xy_m) & (nav.nodes_m[:, :2] <= r.max_xy_m), axis=1)
    assert np.all(on_floor | in_stairwell)
    # Tables and beds exist in these houses, so the rule above had something to reject.
    assert any(o.label in ("table", "bed", "coffee table") for o in robot.scene.objects)


@pytest.mark.parametrize("spec", ["generated:0:floors=3", "generated:2:area=100:floors=3"])
def test_three_floors_joined_by_one_flight_per_pair_of_floors(spec):
    from libs.world.navgrid import NavGrid
    from libs.world.house import STOREY_H

    scene = generate_house(spec)
    assert scene.floors == 3
    shafts = [r for r in scene.rooms if r.room_type == "staircase" and "landing" not in r.name]
    assert sorted(r.floor for r in shafts) == [0, 1]
    nav = NavGrid(scene)
    main = nav.component == nav.main_component
    start = scene.start_pose.xyz
    for fl in range(3):
        rooms = [r for r in scene.rooms if r.floor == fl and r.room_type != "staircase"]
        assert rooms, f"no rooms on floor {fl}"
        for room in rooms:
            cells = _room_floor_nodes(nav, room)
            assert len(cells) > 50 and main[cells].mean() > 0.5, room.name
        goal = nav.nodes_m[_room_floor_nodes(nav, rooms[0])[0]]
        assert abs(goal[2] - fl * STOREY_H) < 0.05
        path = nav.shortest_path(start, goal, smooth=False)
        assert path is not None, f"floor {fl} unreachable"
        assert np.max(np.abs(np.diff(path[:, 2])), initial=0.0) <= 0.2 + 1e-6


def test_large_house_areas_up_to_1200_m2():
    s = generate_house("generated:3:area=1200")
    area = sum(r.area_m2 for r in s.rooms if r.room_type != "staircase")
    assert 1100 <= area <= 1300
    assert len(s.rooms) > 40 and len(s.objects) > 100


def test_furniture_catalogue_builds_every_kind_a_room_asks_for():
    from libs.world.furniture import FURNITURE, ROOM_FURNITURE, furniture_item

    for kinds in ROOM_FURNITURE.values():
        assert set(kinds) <= set(FURNITURE)
    rng = np.random.default_rng(0)
    for kind, f in FURNITURE.items():
        label, colour, w, d, h, parts, placement = furniture_item(kind, rng)
        assert label == f.label and placement == f.placement and w in f.widths_m
        assert colour in f.colours or colour == f.described_as
        assert w > 0 and d > 0 and h > 0 and parts
        assert all(p[0] in ("box", "cyl") for p in parts)
    with pytest.raises(ValueError):
        furniture_item("spaceship", rng)
