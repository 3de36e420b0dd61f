"""Curated clouds sampled from meshes, and the generated evaluation set (determinism, format)."""

from __future__ import annotations

import json

import numpy as np
from shared.o3d import o3d
import pytest

from tests.unit.evaluation.conftest import box_scene
from evaluation.clouds import sample_scene_cloud, visible_from
from shared.cloud import encode, view_dirs_unit
from evaluation.dataset import SetSpec, generate_set, gt_path_for, parse_floors, write_set
from evaluation.errors import ConfigError
from libs.world import read_episodes, read_ground_truth


def test_cloud_is_area_uniform_on_the_surface_with_labels_and_colours():
    scene = box_scene()
    cloud = sample_scene_cloud(scene, density_per_m2=400.0, seed=3)
    total = 2 * (4 * 3 + 4 * 2.5 + 3 * 2.5)
    assert len(cloud) == round(total * 400)
    xyz = cloud.xyz.astype(np.float64)
    # Every point lies on one of the six faces of the box.
    on_face = (np.isclose(xyz[:, 0], 0, atol=1e-5) | np.isclose(xyz[:, 0], 4, atol=1e-5)
               | np.isclose(xyz[:, 1], 0, atol=1e-5) | np.isclose(xyz[:, 1], 3, atol=1e-5)
               | np.isclose(xyz[:, 2], 0, atol=1e-5) | np.isclose(xyz[:, 2], 2.5, atol=1e-5))
    assert on_face.all()
    # The floor (label 1) holds its share of the area, and is exactly the z = 0 points.
    floor = cloud.labels == 1
    assert floor.mean() == pytest.approx(12 / total, abs=0.01)
    assert np.array_equal(floor, np.isclose(xyz[:, 2], 0, atol=1e-5) & (cloud.labels != 0))
    # Uniform within a face: the floor's quadrants each get a quarter.
    f = xyz[floor]
    q = (f[:, 0] < 2).astype(int) * 2 + (f[:, 1] < 1.5).astype(int)
    assert np.bincount(q, minlength=4) / len(f) == pytest.approx([0.25] * 4, abs=0.03)
    assert (cloud.rgb == [204, 51, 26]).all()
    assert np.array_equal(sample_scene_cloud(scene, density_per_m2=400.0, seed=3).xyz, cloud.xyz)
    capped = sample_scene_cloud(scene, density_per_m2=400.0, max_points=1000)
    assert len(capped) == 1000
    # ... and still evenly spread (sampled again at the capped density, not thinned at random, which
    # left floor gaps of 1.4-2.4 spacings): no point of the floor farther than 1.3 spacings from one.
    from scipy.spatial import cKDTree

    floor_xyz = capped.xyz[np.isclose(capped.xyz[:, 2], 0, atol=1e-5)].astype(np.float64)
    probes = np.stack(np.meshgrid(np.linspace(0, 4, 200), np.linspace(0, 3, 150)), -1).reshape(-1, 2)
    gap = cKDTree(floor_xyz).query(np.c_[probes, np.zeros(len(probes))])[0].max()
    assert gap < 1.3 * np.sqrt(12.0 / len(floor_xyz)), gap


def test_ply_reads_back_with_open3d_and_keeps_labels(tmp_path):
    cloud = sample_scene_cloud(box_scene(), density_per_m2=50.0, seed=1)
    data = encode(cloud)
    path = tmp_path / "c.ply"
    path.write_bytes(data)
    pcd = o3d.io.read_point_cloud(str(path))
    assert np.allclose(np.asarray(pcd.points), cloud.xyz, atol=1e-6)
    assert np.allclose(np.asarray(pcd.colors) * 255, cloud.rgb, atol=0.5)
    head, _, body = data.partition(b"end_header\n")
    names = next(ln for ln in head.decode().splitlines() if ln.startswith("comment label_names "))
    assert json.loads(names.split(" ", 2)[2]) == {"0": "wall", "1": "floor"}
    # A curated cloud records where its points were seen from: char view_x/y/z after the label.
    rec = np.frombuffer(body, np.dtype([("p", "<f4", 3), ("c", "u1", 3), ("label", "<i4"), ("view", "i1", 3)]))
    assert np.array_equal(rec["label"], cloud.labels)
    assert np.array_equal(rec["view"], cloud.view_dirs)


def test_set_spec_houses_cycle_floors_and_validate():
    spec = SetSpec(houses=3, per_house=1, floors=(1, 2), seed=2)
    assert spec.scene_specs() == ["generated:2000", "generated:2001:floors=2", "generated:2002"]
    assert parse_floors("1, 2") == (1, 2)
    for bad in ({"floors": (3,)}, {"houses": 0}, {"min_geodesic_m": 9.0, "max_geodesic_m": 5.0}):
        with pytest.raises(ConfigError):
            SetSpec(**bad)
    assert gt_path_for("a/b.json.gz").name == "b_gt.json.gz" and gt_path_for("b.json").name == "b_gt.json"


@pytest.fixture(scope="module")
def small_set():
    return generate_set(SetSpec(houses=2, per_house=2, floors=(1, 2), seed=0), with_gt=True)


def test_generated_set_is_deterministic_and_in_r2r_ce_format(small_set, tmp_path):
    ds, gt = small_set
    assert [e.episode_id for e in ds.episodes] == [1, 2, 3, 4]
    assert [e.scene_id for e in ds.episodes] == ["generated:0"] * 2 + ["generated:1:floors=2"] * 2
    vocab = ds.extra["instruction_vocab"]
    for e in ds.episodes:
        assert {"episode_id", "trajectory_id", "scene_id", "start_position", "start_rotation", "info", "goals",
                "instruction", "reference_path"} <= set(e.raw)
        assert 5.0 <= e.geodesic_distance_m <= 20.0
        toks = [t for t in e.raw["instruction"]["instruction_tokens"] if t]
        assert [vocab["itos"][t] for t in toks][:3] == [w.strip(".,").lower() for w in e.instruction.split()][:3]
        # The dense ground truth starts at the start and ends near the goal (oracle stop radius 0.5 m).
        locs = gt[str(e.episode_id)].locations_m
        assert np.allclose(locs[0][:2], e.start_pose.xyz[:2]) and np.linalg.norm(locs[-1][:2] - e.goal_m[:2]) <= 0.5
    paths = write_set(ds, gt, tmp_path / "set.json.gz")
    again = read_episodes(paths[0])
    assert [e.raw for e in again.episodes] == [e.raw for e in ds.episodes]
    assert set(read_ground_truth(paths[1])) == {"1", "2", "3", "4"}
    # Same spec, same bytes.
    ds2, _ = generate_set(SetSpec(houses=2, per_house=2, floors=(1, 2), seed=0), with_gt=False)
    paths2 = write_set(ds2, {}, tmp_path / "again.json.gz")
    assert paths2[0].read_bytes() == paths[0].read_bytes() and len(paths2) == 1


def test_curated_cloud_keeps_only_surfaces_seen_from_walkable_space():
    # The box room plus a closed 1 m crate on its floor and a ceiling slab 0.2 m thick above it:
    # the crate's underside, the floor under it and the slab's top and edges are hidden from any
    # eye position in the room; the crate's top and sides, the walls and the ceiling are seen.
    room = box_scene()
    parts = [(room.vertices, room.triangles, room.triangle_labels)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    cube_tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int32)
    for lo, hi, label in (((1.5, 1.0, 0.0), (2.5, 2.0, 1.0), 2), ((0.0, 0.0, 2.5), (4.0, 3.0, 2.7), 3)):
        v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])], float)
        parts.append((v, cube_tris, np.full(12, label, np.int32)))
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    scene = type(room)(
        name="crate", vertices=np.concatenate([p[0] for p in parts]),
        triangles=np.concatenate([p[1] + o for p, o in zip(parts, offsets)]).astype(np.int32),
        vertex_colors=np.full((sum(len(p[0]) for p in parts), 3), 0.5, np.float32),
        triangle_labels=np.concatenate([p[2] for p in parts]), label_names={0: "wall", 1: "floor", 2: "crate", 3: "slab"})
    eyes = np.array([[x, y, h] for x in (0.5, 3.5) for y in (0.5, 2.5) for h in (0.6, 1.25)])
    cloud = sample_scene_cloud(scene, density_per_m2=400.0, seed=2, viewpoints_m=eyes, nearest_viewpoints=8)
    xyz, lab = cloud.xyz.astype(np.float64), cloud.labels
    under_crate = (xyz[:, 2] < 0.01) & (np.abs(xyz[:, 0] - 2.0) < 0.45) & (np.abs(xyz[:, 1] - 1.5) < 0.45)
    assert not under_crate.any()  # floor under the crate and the crate's underside
    assert not (xyz[:, 2] > 2.55).any()  # the slab's top and the slab's edges above the ceiling
    crate_top = (lab == 2) & (xyz[:, 2] > 0.99)
    assert crate_top.sum() == pytest.approx(400.0, rel=0.15)  # seen from 1.25 m: kept at the density
    walls = (lab == 0)  # the room's four walls and its ceiling face all face the inside
    assert walls.sum() == pytest.approx(400.0 * (2 * (4 + 3) * 2.5 + 12), rel=0.05)
    # Each point records the side it was seen from: the crate's top upwards, the walls inwards.
    towards = view_dirs_unit(cloud.view_dirs)
    top_inside = crate_top & (np.abs(xyz[:, 0] - 2.0) < 0.45) & (np.abs(xyz[:, 1] - 1.5) < 0.45)  # not its sides
    assert (towards[top_inside, 2] > 0.05).all()  # from eyes 0.25 m above it, 1.5-2 m away
    west_wall = (lab == 0) & (xyz[:, 0] < 0.01)
    assert west_wall.sum() > 100 and (towards[west_wall, 0] > 0.2).all()
    everything = sample_scene_cloud(scene, density_per_m2=400.0, seed=2, visible_only=False)
    assert len(cloud) < 0.85 * len(everything)  # 16.8 of 91.8 m2 are hidden


def test_visible_from_gives_the_same_answer_whatever_its_chunk():
    # visible_from goes through the points a chunk at a time (16k: small temporaries); each point's answer
    # is its own, so a chunk that cuts the points anywhere, or none, changes no bit of the mask or the
    # directions.
    scene = box_scene()
    rng = np.random.default_rng(3)
    xyz = rng.uniform([-1.0, -1.0, -0.5], [5.0, 4.0, 3.0], (5000, 3))  # inside the room (seen) and outside (hidden)
    eyes = np.array([[x, y, 1.2] for x in (0.5, 2.0, 3.5) for y in (0.5, 2.5)])
    whole, whole_dirs = visible_from(scene, xyz, eyes, nearest=4, chunk=len(xyz), with_dirs=True)
    assert 0 < whole.sum() < len(xyz)
    for chunk in (1, 7, 1000, 4999):
        seen, dirs = visible_from(scene, xyz, eyes, nearest=4, chunk=chunk, with_dirs=True)
        assert np.array_equal(seen, whole) and np.array_equal(dirs, whole_dirs)
