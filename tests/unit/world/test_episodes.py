"""R2R-CE episodes: exact round trip of the real file, world conversion, generation."""

from __future__ import annotations

import gzip
import math

import numpy as np
import pytest

from libs.world.episodes import (
    Episode,
    generate_episodes,
    ground_truth_for,
    read_episodes,
    read_ground_truth,
    write_episodes,
    write_ground_truth,
)
from libs.world.errors import SceneNotFoundError
from shared.schemas import Pose

R2R = "r2r_ce/R2R_VLNCE_v1-3_preprocessed_val_unseen.json.gz"


def test_real_r2r_ce_file_round_trips_exactly(shared_data, tmp_path):
    src = shared_data / R2R
    ds = read_episodes(src)
    assert len(ds.episodes) == 1839
    out = write_episodes(ds, tmp_path / "copy.json.gz")
    with gzip.open(src, "rb") as a, gzip.open(out, "rb") as b:
        assert a.read() == b.read()


def test_real_episode_in_world_frame(shared_data):
    ep = read_episodes(shared_data / R2R).episodes[0]
    raw = ep.raw
    # Habitat y-up -> world z-up: height is Habitat y, world y is minus Habitat z.
    assert ep.start_pose.position_m == pytest.approx((raw["start_position"][0], -raw["start_position"][2], raw["start_position"][1]))
    assert ep.goal_m[2] == pytest.approx(raw["goals"][0]["position"][1])
    assert ep.reference_path_m.shape == (len(raw["reference_path"]), 3)
    assert ep.goal_radius_m == 3.0 and ep.geodesic_distance_m == pytest.approx(raw["info"]["geodesic_distance"])


def test_missing_scene_names_file_and_directory(shared_data, tmp_path):
    ep = read_episodes(shared_data / R2R).episodes[0]
    with pytest.raises(SceneNotFoundError) as exc:
        ep.scene_path(tmp_path)
    msg = str(exc.value)
    assert ep.scene_id in msg and str(tmp_path) in msg


def test_from_world_conversion_is_consistent():
    pose = Pose(position_m=(1.0, 2.0, 0.5), heading_rad=0.7)
    ep = Episode.from_world(3, "generated:0", pose, [4.0, -1.0, 0.5], np.array([[1.0, 2.0, 0.5], [4.0, -1.0, 0.5]]), "Go.", 4.5)
    assert ep.start_pose.position_m == pytest.approx(pose.position_m)
    assert math.isclose(ep.start_pose.heading_rad, 0.7, abs_tol=1e-9)
    assert ep.goal_m == pytest.approx([4.0, -1.0, 0.5])


def test_generated_episodes(house_robot, tmp_path):
    ds = generate_episodes(house_robot.scene, house_robot.nav, 6, seed=2)
    assert len(ds.episodes) == 6
    for ep in ds.episodes:
        assert 5.0 <= ep.geodesic_distance_m <= 20.0
        ref = ep.reference_path_m
        assert np.allclose(ref[0], ep.start_pose.xyz) and np.linalg.norm(ref[-1] - ep.goal_m) < 1e-9
        # Reference waypoints are walkable and the legs between them are straight walkable segments.
        for a, b in zip(ref[:-1], ref[1:]):
            assert house_robot.nav.segment_clear(a, b)
        assert ep.geodesic_distance_m == pytest.approx(house_robot.nav.geodesic_distance(ep.start_pose.xyz, ep.goal_m))
        text = ep.instruction
        assert text.startswith(("Exit", "Turn", "Bear", "Walk")) and "Stop next to the" in text
        goal_room = house_robot.scene.room_at(ep.goal_m)
        assert text.rstrip(".").endswith(f"in the {goal_room.room_type}")
        toks = ep.raw["instruction"]["instruction_tokens"]
        assert len(toks) == 200 and 1 not in toks  # no unknown words
    out = write_episodes(ds, tmp_path / "gen.json.gz")
    again = read_episodes(out)
    assert [e.raw for e in again.episodes] == [e.raw for e in ds.episodes]
    assert write_episodes(again, tmp_path / "gen2.json.gz").read_bytes() == out.read_bytes()
    # The same seed gives the same episodes.
    ds2 = generate_episodes(house_robot.scene, house_robot.nav, 6, seed=2)
    assert [e.raw for e in ds2.episodes] == [e.raw for e in ds.episodes]


GT = "r2r_ce/R2R_VLNCE_v1-3_preprocessed_val_unseen_gt.json.gz"


def test_real_ground_truth_round_trips_exactly(shared_data, tmp_path):
    src = shared_data / GT
    gt = read_ground_truth(src)
    assert len(gt) == 1839
    out = write_ground_truth(gt, tmp_path / "gt.json.gz")
    with gzip.open(src, "rb") as a, gzip.open(out, "rb") as b:
        assert a.read() == b.read()
    # Locations start at the episode start (world frame), one per forward step plus the start.
    eps = read_episodes(shared_data / R2R).by_id()
    for key in list(gt)[:50]:
        rec, ep = gt[key], eps[int(key)]
        assert np.allclose(rec.locations_m[0], ep.start_pose.xyz)
        assert len(rec.locations_m) == rec.forward_steps + 1 == rec.actions.count(1) + 1
        assert rec.actions[-1] == 0 and np.linalg.norm(rec.locations_m[-1] - ep.goal_m) < 0.5


def test_generated_ground_truth_follows_the_oracle(house_robot, tmp_path):
    ds = generate_episodes(house_robot.scene, house_robot.nav, 3, seed=4)
    gt = ground_truth_for(ds, house_robot.nav)
    assert list(gt) == [str(e.episode_id) for e in ds.episodes]
    for ep in ds.episodes:
        rec = gt[str(ep.episode_id)]
        locs = rec.locations_m
        assert np.allclose(locs[0][:2], ep.start_pose.xyz[:2])
        assert rec.actions[-1] == 0 and 0 not in rec.actions[:-1] and set(rec.actions) <= {0, 1, 2, 3}
        assert len(locs) == rec.forward_steps + 1
        steps = np.linalg.norm(np.diff(locs[:, :2], axis=0), axis=1)
        assert np.all(steps <= 0.25 + 1e-6) and np.median(steps) > 0.24
        assert np.linalg.norm(locs[-1][:2] - ep.goal_m[:2]) <= 0.5
        assert all(house_robot.nav.is_navigable(p) for p in locs)
        # An oracle on the shortest path walks little more than the geodesic distance.
        assert steps.sum() < ep.geodesic_distance_m + 1.0
    out = write_ground_truth(gt, tmp_path / "gt.json.gz")
    again = read_ground_truth(out)
    assert {k: v.raw for k, v in again.items()} == {k: v.raw for k, v in gt.items()}
    assert write_ground_truth(again, tmp_path / "gt2.json.gz").read_bytes() == out.read_bytes()
