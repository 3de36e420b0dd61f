"""The simulated robot: observation, motion with collisions, recording, registry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from libs.world.errors import SceneNotFoundError
from services.robot_io.core.robot import ROBOTS, SimConfig, SimRobot
from shared.geometry import panorama_headings, wrap_angle
from shared.schemas import CameraIntrinsics, MoveStatus, Pose


def test_panorama_shapes_dtypes_and_headings(house_robot):
    house_robot.reset(Pose(position_m=house_robot.scene.start_pose.position_m, heading_rad=0.3))
    pano = house_robot.observe()
    assert pano.rgb.shape == (12, 64, 64, 3) and pano.rgb.dtype == np.uint8
    assert pano.depth_m.shape == (12, 64, 64) and pano.depth_m.dtype == np.float32
    assert pano.semantic.dtype == np.int32
    assert np.allclose(pano.headings_rad, panorama_headings(0.3))
    assert np.isclose(pano.pose.heading_rad, 0.3)
    # Inside a closed house every ray hits something, at a plausible distance.
    assert np.all(pano.depth_m > 0.05) and np.all(pano.depth_m < 30)
    names = {house_robot.scene.label_names[i] for i in np.unique(pano.semantic)}
    assert "wall" in names and any(n.endswith(" floor") for n in names)
    other = house_robot.observe(CameraIntrinsics(width_px=32, height_px=24, hfov_deg=60), with_semantic=False)
    assert other.rgb.shape == (12, 24, 32, 3) and other.semantic is None


def test_view_zero_looks_along_the_heading(house_robot):
    """The centre pixel of view i sees the wall hit by a horizontal ray along heading - i*30 deg."""
    p = house_robot.scene.start_pose
    house_robot.reset(p)
    pano = house_robot.observe()
    cam_pos = house_robot.true_pose.xyz + np.array([0, 0, 1.25])
    for i, h in enumerate(pano.headings_rad):
        d = np.array([math.cos(h), math.sin(h), 0.0])
        t = house_robot.renderer.first_hit_distance(cam_pos, d)
        # 64 px: the optical axis falls between the four centre pixels.
        centre = pano.depth_m[i, 31:33, 31:33]
        assert np.allclose(centre, t, rtol=0.05, atol=0.03), (i, centre, t)


def _crosses_geometry(robot, a, b) -> bool:
    """Horizontal rays at several heights along the segment a->b hit any surface before b?"""
    d = b[:2] - a[:2]
    length = float(np.hypot(*d))
    if length < 1e-6:
        return False
    for h in (0.3, 0.8, 1.2, 1.45):
        o = np.array([a[0], a[1], a[2] + h])
        t = robot.renderer.first_hit_distance(o, np.array([d[0] / length, d[1] / length, 0.0]))
        if t < length:
            return True
    return False


def test_move_to_never_passes_through_walls(house_robot):
    rng = np.random.default_rng(1)
    house_robot.reset()
    blocked = reached = 0
    for _ in range(80):
        a = rng.uniform(-math.pi, math.pi)
        dist = rng.uniform(0.3, 4.0)
        track = []
        orig = house_robot._advance_to

        def spy(new, orig=orig):
            track.append((house_robot._pos.copy(), np.asarray(new).copy()))
            orig(new)

        house_robot._advance_to = spy
        try:
            res = house_robot.move_to(dist * math.cos(a), dist * math.sin(a))
        finally:
            del house_robot._advance_to
        for p0, p1 in track:
            assert np.hypot(*(p1[:2] - p0[:2])) <= house_robot.config.step_m + 1e-9
            assert not _crosses_geometry(house_robot, p0, p1), f"crossed geometry between {p0} and {p1}"
            assert house_robot.nav.is_navigable(p1)
        blocked += res.status == MoveStatus.BLOCKED
        reached += res.status == MoveStatus.REACHED
        assert np.isclose(house_robot.true_pose.heading_rad, wrap_angle(a))
    # Random moves in a furnished house: both outcomes must occur.
    assert blocked > 5 and reached > 5


def test_move_to_reaches_a_free_waypoint_exactly(house_robot):
    nav = house_robot.nav
    house_robot.reset()
    start = house_robot.true_pose.xyz
    # Find a free straight segment of 1.5 m from the start.
    for a in np.linspace(-math.pi, math.pi, 24, endpoint=False):
        goal = start + 1.5 * np.array([math.cos(a), math.sin(a), 0.0])
        if nav.segment_clear(start, goal):
            break
    else:
        pytest.skip("no free direction at the start")
    res = house_robot.move_to(goal[0] - start[0], goal[1] - start[1])
    assert res.status == MoveStatus.REACHED and res.steps == 6
    assert np.allclose(res.pose.xyz[:2], goal[:2], atol=1e-6)
    assert res.travelled_m == pytest.approx(1.5, abs=1e-6)


def test_move_into_a_wall_is_blocked_and_stops_short(house_robot):
    house_robot.reset()
    start = house_robot.true_pose.xyz
    res = house_robot.move_to(18.0, 0.0)  # longer than the house: a wall must stop it
    assert res.status == MoveStatus.BLOCKED
    assert res.travelled_m < 18.0
    assert house_robot.nav.is_navigable(house_robot.true_pose.xyz)
    assert house_robot.true_pose.position_m[0] > start[0]


def test_turn_and_reset(house_robot):
    p0 = house_robot.reset(Pose(position_m=house_robot.scene.start_pose.position_m, heading_rad=0.0))
    assert p0.heading_rad == 0.0
    assert house_robot.turn(math.pi / 2).heading_rad == pytest.approx(math.pi / 2)
    assert house_robot.turn(-math.pi).heading_rad == pytest.approx(-math.pi / 2)
    # Reset onto a wall snaps to the nearest walkable point.
    room = house_robot.scene.rooms[0]
    p = house_robot.reset(Pose(position_m=(room.min_xy_m[0], room.min_xy_m[1], 0.0)))
    assert house_robot.nav.is_navigable(p.xyz)


def test_recording_emits_frames_at_a_fixed_rate(house_robot):
    house_robot.reset()
    frames = []
    with house_robot.recording(frames.append, rate_hz=5.0):
        house_robot.turn(math.radians(90))
        look = house_robot.look_around()
    dt = np.diff([f.timestamp_s for f in frames])
    assert len(frames) > 10 and np.allclose(dt, 0.2)
    assert all(f.rgb.shape == (64, 64, 3) and f.depth_m.shape == (64, 64) for f in frames)
    pitches = [f.pitch_rad for f in look]
    yaws = [wrap_angle(f.pose.heading_rad - look[0].pose.heading_rad) for f in look]
    assert max(pitches) == pytest.approx(math.radians(45)) and min(pitches) == pytest.approx(math.radians(-45))
    assert max(yaws) == pytest.approx(math.radians(60)) and min(yaws) == pytest.approx(math.radians(-60))
    assert house_robot.true_pose.heading_rad == pytest.approx(look[0].pose.heading_rad)
    n = len(frames)
    house_robot.turn(1.0)  # recording closed: nothing more arrives
    assert len(frames) == n


def test_noise_is_off_by_default_and_seeded_when_on():
    cfg = dict(scene="generated:2:area=80", camera={"width_px": 32, "height_px": 32})
    clean = SimRobot(SimConfig(**cfg))
    noisy_cfg = dict(cfg, noise={"seed": 3, "depth_noise_rel": 0.01, "depth_hole_fraction": 0.1, "odometry_drift_per_m": 0.05})
    n1, n2 = SimRobot(SimConfig(**noisy_cfg)), SimRobot(SimConfig(**noisy_cfg))
    a, b, c = clean.observe(), n1.observe(), n2.observe()
    assert np.array_equal(b.depth_m, c.depth_m)
    assert (a.depth_noise_rel, b.depth_noise_rel) == (0.0, 0.01)  # the panorama declares its noise
    holes = (b.depth_m == 0) & (a.depth_m > 0)
    assert 0.05 < holes.mean() < 0.15
    both = (b.depth_m > 0) & (a.depth_m > 0)
    assert not np.array_equal(a.depth_m[both], b.depth_m[both])
    for r in (clean, n1):
        r.move_to(0.5, 0.0)
    assert clean.pose == clean.true_pose
    assert n1.pose != n1.true_pose


def test_registry_and_missing_scene(tmp_path):
    assert "sim" in ROBOTS.names()
    with pytest.raises(SceneNotFoundError) as exc:
        ROBOTS.create("sim", {"scene": "mp3d/abc/abc.glb", "scenes_dir": str(tmp_path)})
    assert "abc.glb" in str(exc.value) and str(tmp_path) in str(exc.value)


def test_scene_info_is_typed_and_json_friendly(two_floor_robot):
    import json

    from shared.schemas import SceneSummary

    info = two_floor_robot.scene_info()
    assert isinstance(info, SceneSummary)
    scene = two_floor_robot.scene
    assert info.floors == 2 and info.triangle_count == len(scene.triangles)
    assert [r.name for r in info.rooms] == [r.name for r in scene.rooms]
    assert len(info.objects) == len(scene.objects) >= 15
    assert info.objects[0].description == scene.objects[0].description
    assert info.label_names[scene.label_id("wall")] == "wall"
    assert info.reachable_area_m2 == pytest.approx(two_floor_robot.nav.reachable_area_m2) and info.reachable_area_m2 > 50
    lo, hi = scene.bounds_m
    assert info.bounds_min_m == pytest.approx(tuple(lo)) and info.bounds_max_m == pytest.approx(tuple(hi))
    dumped = info.model_dump()
    assert dumped["rooms"][0]["room_type"] and dumped["start_pose"]["position_m"] == scene.start_pose.position_m
    text = json.dumps(info.model_dump(mode="json"))
    assert SceneSummary.model_validate_json(text) == info
    # Rooms reach from their floor to the storey above (or the scene's top), as the scene says.
    ground = [r for r in info.rooms if r.floor == 0]
    upper = [r for r in info.rooms if r.floor == 1]
    assert ground and upper
    assert all(r.bounds_max_m[2] == pytest.approx(upper[0].bounds_min_m[2]) for r in ground)
    assert all(r.bounds_max_m[2] == pytest.approx(hi[2]) for r in upper)
    assert info.room(ground[0].name) == ground[0]
