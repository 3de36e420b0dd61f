"""The z-buffer rasteriser against Embree's ``cast_rays`` on the same rays (raster.py states the tolerance)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from services.robot_io.core import raster, render, shading
from services.robot_io.core.raster import MISS_ID, NEAR_M, RasterScene
from services.robot_io.core.render import Intrinsics, SceneRenderer
from services.robot_io.core.robot import SimConfig, SimRobot
from libs.world.scene import Scene, load_scene
from services.robot_io.core.shading import shade
from services.robot_io.tools.raster_parity import (
    DEPTH_RTOL,
    DEPTH_RTOL_COS,
    Parity,
    compare,
    embree_hits,
    raster_hits,
    rays_of,
)
from shared.geometry import PinholeCamera, camera_pose, camera_poses, panorama_headings

pytestmark = pytest.mark.skipif(not shading.AVAILABLE, reason="the rasteriser needs numba")

SQUARE = Intrinsics.from_pinhole(PinholeCamera(96, 96, 90.0))
# Non-square pixels, an off-centre principal point, a non-square image.
SKEWED = Intrinsics(fx=61.0, fy=83.5, cx=40.3, cy=29.8, width_px=88, height_px=70)
UV_ATOL = 5e-3  # Embree's float32 barycentrics of small or grazing triangles


def _scene(vertices, triangles, labels=None) -> Scene:
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    cols = np.random.default_rng(0).uniform(0, 1, (len(v), 3)).astype(np.float32)
    return Scene("test", v, t, cols, np.arange(len(t), dtype=np.int32) if labels is None else labels)


def _check(scene: Scene, poses: np.ndarray, k: Intrinsics, renderer: SceneRenderer | None = None) -> Parity:
    """Compare the two casters on ``poses``; assert the module's tolerance and that colours and labels
    follow the triangle; return the counts."""
    renderer = renderer or SceneRenderer(scene, ray_caster="embree")
    raster = RasterScene(scene.vertices, scene.triangles)
    rays = rays_of(poses, k)
    e, r = embree_hits(renderer.raycasting_scene, rays), raster_hits(raster, poses, k)
    p = compare(scene, rays, e, r)
    # A hit against a miss only where a ray grazes a silhouette edge within rounding (none measured
    # on the houses, Replica or the Habitat assets).
    assert p.miss_off_edge == 0 and p.miss_mismatch <= 1e-4 * p.pixels, p
    assert p.other == 0, p  # every differing pixel is on an edge or where both hit at the same depth
    assert p.same_but_zfight_fraction >= 0.999, p
    assert p.depth_rel_max <= DEPTH_RTOL and p.depth_rel_cos_max <= DEPTH_RTOL_COS, p
    assert p.uv_abs_max <= UV_ATOL, p
    tables = renderer._tables
    rgb_e, lab_e = shade(tables, e["primitive_ids"].copy(), e["primitive_uvs"], e["t_hit"].copy(), True)
    rgb_r, lab_r = shade(tables, r["primitive_ids"].copy(), r["primitive_uvs"], r["t_hit"].copy(), True)
    same = e["primitive_ids"] == r["primitive_ids"]
    assert np.array_equal(lab_e[same], lab_r[same])
    # A blend that rounds the other way, a texel boundary: rare, and only where u, v differ in float32.
    assert np.mean(np.all(rgb_e[same] == rgb_r[same], axis=1)) >= 0.999
    return p


def _robot_poses(robot: SimRobot, n: int, pitch_rad: float, seed: int, nodes: np.ndarray | None = None) -> np.ndarray:
    rng = np.random.default_rng(seed)
    nodes = robot.nav.nodes_m if nodes is None else nodes
    return np.concatenate([camera_poses(nodes[rng.integers(len(nodes))], panorama_headings(rng.uniform(-3, 3), 12),
                                        pitch_rad, robot.config.camera_height_m) for _ in range(n)])


# --- conventions and corner cases ----------------------------------------------------------------


@pytest.mark.parametrize("order", [(0, 1, 2), (0, 2, 1), (2, 0, 1)])
def test_uvs_are_embrees_weights_of_the_second_and_third_vertex(order):
    # (Corners off the pixel grid's lines: a ray exactly on a silhouette edge may go either way.)
    v = np.array([[-1.0, -1.013, 2.0], [1.5, -1.0, 2.5], [-1.017, 1.2, 1.8]])
    scene = _scene(v, [order])
    k = Intrinsics(30.0, 30.0, 15.5, 15.5, 32, 32)
    pose = np.eye(4)
    r = raster_hits(RasterScene(scene.vertices, scene.triangles), pose[None], k)
    e = embree_hits(SceneRenderer(scene, ray_caster="embree").raycasting_scene, rays_of(pose[None], k))
    hit = r["primitive_ids"] != MISS_ID
    assert hit.sum() > 100 and np.array_equal(hit, e["primitive_ids"] != MISS_ID)
    assert np.abs(r["primitive_uvs"][hit] - e["primitive_uvs"][hit]).max() < 1e-5
    # Reconstruct the hit point from (u, v): (1 - u - v) p0 + u p1 + v p2 is t times the ray.
    j, i = np.meshgrid(np.arange(32), np.arange(32))
    d = np.stack([(j - k.cx) / k.fx, (i - k.cy) / k.fy, np.ones_like(j, float)], -1).reshape(-1, 3)[hit]
    p = v[list(order)]
    uv = r["primitive_uvs"][hit].astype(np.float64)
    point = (1 - uv.sum(1))[:, None] * p[0] + uv[:, :1] * p[1] + uv[:, 1:] * p[2]
    assert np.abs(point - r["t_hit"][hit, None] * d).max() < 1e-5


def test_both_faces_are_hit_and_degenerate_triangles_never():
    v = [[-1, -1, 2], [1, -1, 2], [-1, 1, 2],  # facing the camera (counter-clockwise seen from it)
         [1, 1, 3], [1, -1, 3], [-1, 1, 3],  # the other winding, behind it: seen where the first is not
         [0, 0, 1], [0.5, 0.5, 1], [1, 1, 1],  # collinear
         [0.2, 0.3, 1.5], [0.2, 0.3, 1.5], [0.6, -0.4, 1.5],  # a repeated vertex
         [0.0, -1, 1], [0.0, 1, 1], [0.0, 0, 4]]  # edge-on: its plane x = 0 holds the camera centre
    scene = _scene(v, np.arange(15).reshape(5, 3))
    pose = np.eye(4)[None]
    p = _check(scene, pose, SQUARE)
    assert p.prim_diff == 0
    r = raster_hits(RasterScene(scene.vertices, scene.triangles), pose, SQUARE)
    assert set(np.unique(r["primitive_ids"])) == {0, 1, MISS_ID}


def test_an_empty_scene_misses_everywhere():
    r = raster_hits(RasterScene(np.zeros((0, 3)), np.zeros((0, 3), np.int64)), np.eye(4)[None], SKEWED)
    assert np.all(r["primitive_ids"] == MISS_ID) and np.all(np.isinf(r["t_hit"])) and not r["primitive_uvs"].any()


def test_chunks_at_equal_depth_are_drawn_in_numbas_argsort_order():
    """The draw order of equal keys decides z-fights: _argsort must put ties where numba's np.argsort
    (its quicksort, run here as plain Python from numba's own source) puts them, not merely sort."""
    from numba.misc.quicksort import make_py_quicksort  # numba is optional: see pytestmark

    reference = make_py_quicksort(is_argsort=True, is_np_array=True).run_quicksort
    rng = np.random.default_rng(5)
    for n in (0, 1, 2, 14, 15, 16, 40, 333):
        for key in (rng.integers(0, max(n // 8, 1), n).astype(np.float64), rng.uniform(0, 1, n), np.zeros(n)):
            rank = np.full(n + 3, -1, np.int64)
            raster._argsort(np.concatenate([key, [-1.0, -1.0, -1.0]]), n, rank)  # only key[:n] is sorted
            assert rank[:n].tolist() == reference(key).tolist(), (n, key)


def test_triangles_behind_and_across_the_camera_plane():
    # A floor under the camera reaching far behind it, a wall beside it from behind to in front, a
    # triangle entirely behind it: the parts in front are drawn, without clipping.
    # (Camera frame = world frame here: x right, y down, looking along +z.)
    v = [[-50, 1.2, -50], [50, 1.2, -50], [0, 1.2, 60],
         [-1, -2, -3], [-1, -2, 5], [-1, 2, 5],
         [-1, -1, -2], [1, -1, -2], [0, 1, -0.5]]
    scene = _scene(v, np.arange(9).reshape(3, 3))
    poses = np.stack([np.eye(4), _rot_y(-1.2), _rot_y(0.9) @ _rot_x(-0.6), _rot_y(3.0)])
    p = _check(scene, poses, SKEWED)
    assert p.prim_diff <= 2  # a shared-depth seam at most
    r = raster_hits(RasterScene(scene.vertices, scene.triangles), np.eye(4)[None], SKEWED)
    assert {0, 1} <= set(np.unique(r["primitive_ids"])) and 2 not in set(np.unique(r["primitive_ids"]))


def test_surfaces_nearer_than_the_near_plane_are_seen_through():
    d, s = 0.5 * NEAR_M, 0.005 * NEAR_M
    v = [[-5, -5, 2], [5, -5, 2], [0, 5, 2],  # a wall at 2 m
         [-s, -s, d], [s, -s, d], [0, s, d],  # a speck at NEAR_M / 2 on the optical axis
         [-1.5 * NEAR_M, -1.5 * NEAR_M, 3 * NEAR_M], [-0.5 * NEAR_M, -1.5 * NEAR_M, 3 * NEAR_M],
         [-1.5 * NEAR_M, -0.5 * NEAR_M, 3 * NEAR_M]]  # a sliver at 3 NEAR_M, upper left
    scene = _scene(v, np.arange(9).reshape(3, 3))
    k = Intrinsics(20.0, 20.0, 10.0, 10.0, 21, 21)  # pixel (10, 10) looks down the axis
    pose = np.eye(4)[None]
    e = embree_hits(SceneRenderer(scene, ray_caster="embree").raycasting_scene, rays_of(pose, k))
    r = raster_hits(RasterScene(scene.vertices, scene.triangles), pose, k)
    centre = 10 * 21 + 10
    assert e["primitive_ids"][centre] == 1 and r["primitive_ids"][centre] == 0
    assert abs(r["t_hit"][centre] - 2.0) < 1e-6
    elsewhere = np.arange(21 * 21) != centre
    assert np.array_equal(e["primitive_ids"][elsewhere], r["primitive_ids"][elsewhere])
    assert 2 in set(r["primitive_ids"])  # 3 x the near plane away is seen


def test_a_finely_tessellated_wall_has_no_cracks():
    # 40 x 40 quads, tilted, at a random rotation: shared edges leave no pixel unhit.
    n = 40
    g = np.linspace(-4, 4, n + 1)
    x, y = np.meshgrid(g, g)
    v = np.stack([x.ravel(), y.ravel(), 3 + 0.3 * x.ravel() + 0.1 * y.ravel()], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    t = np.concatenate([np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1]], -1).reshape(-1, 3),
                        np.stack([idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 3)])
    scene = _scene(v, t)
    poses = np.stack([np.eye(4), _rot_y(0.3) @ _rot_x(0.2)])
    _check(scene, poses, SKEWED)
    r = raster_hits(RasterScene(scene.vertices, scene.triangles), np.eye(4)[None], SKEWED)
    assert np.all(r["primitive_ids"] != MISS_ID)  # the wall fills the view: any crack is a miss


def _rot_x(a):
    m = np.eye(4)
    m[1:3, 1:3] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return m


def _rot_y(a):
    m = np.eye(4)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    return m


# --- generated houses ----------------------------------------------------------------------------


@pytest.mark.parametrize("pitch_deg", [0.0, 45.0, -45.0])
def test_one_floor_house(house_robot, pitch_deg):
    _check(house_robot.scene, _robot_poses(house_robot, 3, math.radians(pitch_deg), seed=1), SQUARE, house_robot.renderer)


def test_one_floor_house_non_square_intrinsics(house_robot):
    poses = np.concatenate([_robot_poses(house_robot, 2, p, seed=2) for p in (0.0, 0.6, -0.7)])
    _check(house_robot.scene, poses, SKEWED, house_robot.renderer)


@pytest.mark.parametrize("pitch_deg", [0.0, 45.0, -45.0])
def test_two_floor_house_with_stairs(two_floor_robot, pitch_deg):
    robot = two_floor_robot
    z = robot.nav.nodes_m[:, 2]
    floors = sorted({r.floor_z_m for r in robot.scene.rooms if r.room_type != "staircase"})
    stairs = robot.nav.nodes_m[np.all(np.abs(z[:, None] - np.array(floors)[None]) > 0.1, axis=1)]
    assert len(stairs) > 0 and len(floors) == 2
    poses = np.concatenate([_robot_poses(robot, 2, math.radians(pitch_deg), seed=3),
                            _robot_poses(robot, 2, math.radians(pitch_deg), seed=4, nodes=stairs)])
    _check(robot.scene, poses, SQUARE, robot.renderer)


def test_camera_a_robot_radius_from_a_wall(house_robot):
    robot = house_robot
    rng = np.random.default_rng(5)
    poses = []
    for _ in range(40):
        p = robot.nav.nodes_m[rng.integers(len(robot.nav.nodes_m))] + [0, 0, robot.config.camera_height_m]
        a = rng.uniform(-math.pi, math.pi)
        d = np.array([math.cos(a), math.sin(a), 0.0])
        dist = float(robot.renderer.first_hit_distance(p, d))
        if math.isfinite(dist) and dist > 0.3:
            cam = p + (dist - 0.1) * d  # 0.1 m from the wall, facing it, then turning along it
            poses += [camera_pose(cam, a + turn, pitch, 0.0) for turn in (0.0, 0.8, -1.2) for pitch in (0.0, 0.7)]
        if len(poses) >= 24:
            break
    assert len(poses) >= 24
    p = _check(robot.scene, np.stack(poses), SKEWED, robot.renderer)
    assert p.pixels == len(poses) * SKEWED.width_px * SKEWED.height_px


# --- real scenes ---------------------------------------------------------------------------------


def _orbit(scene: Scene, inside: bool) -> np.ndarray:
    """12 views from the middle of the scene's box (a panorama at three pitches), or from a ring
    around it looking in."""
    lo, hi = scene.vertices.min(0), scene.vertices.max(0)
    c = (lo + hi) / 2
    if inside:
        return np.concatenate([camera_poses(c, panorama_headings(0.3, 4), p, 0.0) for p in (0.0, 0.7, -0.7)])
    r = 0.6 * np.linalg.norm(hi - lo)
    poses = []
    for i in range(12):
        a = i * math.pi / 6
        p = c + r * np.array([math.cos(a), math.sin(a), 0.0])
        poses.append(camera_pose(p, math.atan2(c[1] - p[1], c[0] - p[0]), (0.0, 0.4, -0.4)[i % 3], 0.0))
    return np.stack(poses)


def test_replica_office(shared_data):
    root = shared_data / "replica_office0"
    scene = load_scene(str(root / "office0_mesh.ply"))
    recorded = np.loadtxt(root / "traj.txt", max_rows=40).reshape(-1, 4, 4)[::4]
    k = Intrinsics(120.0, 120.0, 63.5, 47.5, 128, 96)
    renderer = SceneRenderer(scene, ray_caster="embree")
    _check(scene, recorded, k, renderer)
    _check(scene, _orbit(scene, inside=True), SKEWED, renderer)


@pytest.mark.parametrize("name", ["simple_room.glb", "stage_floor1.glb", "chair.glb", "fridge_body.glb"])
def test_habitat_test_assets(shared_data, name):
    scene = load_scene(str(shared_data / "habitat_test_assets" / name))
    renderer = SceneRenderer(scene, ray_caster="embree")
    p = _check(scene, _orbit(scene, inside=False), SQUARE, renderer)
    p = p + _check(scene, _orbit(scene, inside=True), SKEWED, renderer)
    assert p.pixels - p.prim_diff > 0


# --- selection -----------------------------------------------------------------------------------


def test_auto_picks_raster_below_the_crossover_and_embree_above(monkeypatch):
    # 200 triangles: raster for views of 17 pixels or more at 12 triangles per pixel.
    scene = _scene(np.random.default_rng(1).uniform(-1, 1, (600, 3)) + [0, 0, 3], np.arange(600).reshape(200, 3))
    auto, embree, raster = (SceneRenderer(scene, ray_caster=n) for n in ("auto", "embree", "raster"))
    assert render.RASTER_TRIANGLES_PER_PIXEL == 12
    assert auto.caster_for(5, 4) == "raster" and auto.caster_for(4, 4) == "embree"
    assert embree.caster_for(256, 256) == "embree" and raster.caster_for(1, 1) == "raster"
    assert render.resolve_ray_caster("auto", 49152, 64 * 64) == "raster"
    assert render.resolve_ray_caster("auto", 49153, 64 * 64) == "embree"
    # Each answers render() with the backend it names (the rasteriser is built on first use) ...
    pose = np.eye(4)
    for r, k, used in ((auto, Intrinsics(4, 4, 1.5, 1.5, 4, 4), False), (auto, Intrinsics(5, 5, 2, 2, 5, 5), True)):
        r.render(pose, k)
        assert (r._raster is not None) == used
    # ... and gives the same picture either way.
    k = Intrinsics(30.0, 30.0, 15.5, 15.5, 32, 32)
    a, b = embree.render(pose, k), raster.render(pose, k)
    assert np.array_equal(a.depth_m > 0, b.depth_m > 0) and np.allclose(a.depth_m, b.depth_m, rtol=DEPTH_RTOL, atol=0)
    monkeypatch.setattr(render, "AVAILABLE", False)  # no numba: auto falls back, raster refuses
    assert auto.caster_for(256, 256) == "embree"
    with pytest.raises(RuntimeError):
        SceneRenderer(scene, ray_caster="raster")
    with pytest.raises(ValueError):
        render.resolve_ray_caster("optix", 1, 1)


def test_sim_config_selects_the_caster_and_both_render_the_same_panorama(house_robot):
    with pytest.raises(ValidationError):
        SimConfig(ray_caster="optix")
    assert house_robot.config.ray_caster == "auto" and house_robot.renderer.caster_for(64, 64) == "raster"
    robots = {name: SimRobot(SimConfig(scene=house_robot.config.scene, camera=house_robot.camera, ray_caster=name),
                             scene=house_robot.scene) for name in ("embree", "raster")}
    assert {n: r.renderer.caster_for(64, 64) for n, r in robots.items()} == {"embree": "embree", "raster": "raster"}
    a, b = (robots[n].observe() for n in ("embree", "raster"))
    hit = a.depth_m > 0
    assert np.array_equal(hit, b.depth_m > 0)
    assert np.allclose(a.depth_m, b.depth_m, rtol=DEPTH_RTOL, atol=0)
    # Colours and labels differ only where two coincident faces fight (see test_one_floor_house).
    assert np.mean(np.all(a.rgb == b.rgb, axis=-1)) >= 0.999 and np.mean(a.semantic == b.semantic) >= 0.999
