"""Habitat's own test assets load the right way up, at the right scale and in their real colours."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
from shared.o3d import o3d
import pytest

from libs.world.episodes import Episode, EpisodeDataset, read_episodes, write_episodes
from services.robot_io.core.render import SceneRenderer
from services.robot_io.core.robot import SimConfig, SimRobot
from libs.world.scene import load_scene
from shared.geometry import PinholeCamera, camera_pose, habitat_to_world

ASSETS = "habitat_test_assets"


@pytest.fixture(scope="module")
def assets(shared_data):
    return shared_data / ASSETS


def _floor_normals_up(scene) -> float:
    """Area fraction of the largest horizontal faces whose normal is vertical (|n_z| ~ 1)."""
    v = scene.vertices[scene.triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = np.linalg.norm(n, axis=1)
    nz = np.abs(n[:, 2]) / np.maximum(area, 1e-12)
    return float(area[nz > 0.99].sum() / area.sum())


def test_simple_room_floor_is_horizontal_at_zero_and_walkable(assets):
    robot = SimRobot(SimConfig(scene=str(assets / "simple_room.glb"), camera={"width_px": 32, "height_px": 32}))
    scene = robot.scene
    lo, hi = scene.bounds_m
    # Its stage config says z-up: the 10.5 x 10.8 m floor slab lies in x/y, 2.2 m of room above it.
    assert hi[0] - lo[0] > 10 and hi[1] - lo[1] > 10 and 2.0 < hi[2] - lo[2] < 2.5
    assert _floor_normals_up(scene) > 0.5
    assert robot.nav.reachable_area_m2 > 20.0
    z = robot.true_pose.position_m[2]
    # The slab is 0.2 m thick, centred 4 cm above the origin: its top is at z = 0.145.
    assert abs(z - 0.145) < 0.02, f"the agent stands at z={z:.3f}, not on the floor slab's top at z~0.15"
    # The agent stands on the floor: straight down from the camera the first hit is at its feet.
    d = robot.renderer.first_hit_distance(np.array(robot.true_pose.position_m) + [0, 0, 1.0], np.array([0.0, 0.0, -1.0]))
    assert d == pytest.approx(1.0, abs=0.06)


def test_stage_floor1_honours_up_axis_and_scale_two_and_is_green(assets):
    raw = o3d.io.read_triangle_model(str(assets / "stage_floor1.glb")).meshes[0].mesh
    raw_v = np.asarray(raw.vertices)
    scene = load_scene(str(assets / "stage_floor1.glb"))
    lo, hi = scene.bounds_m
    # y-up file: its x/z extent (20 m) becomes world x/y, doubled by the config's scale [2, 2, 2].
    assert (hi[:2] - lo[:2]) == pytest.approx(2 * (raw_v.max(0) - raw_v.min(0))[[0, 2]], rel=1e-6)
    assert hi[2] - lo[2] == pytest.approx(2 * np.ptp(raw_v[:, 1]), rel=1e-6)
    assert np.allclose(scene.vertices, 2 * habitat_to_world(raw_v))
    # The material's base colour (0.42, 0.80, 0.53) reaches the pixels.
    r = SceneRenderer(scene)
    out = r.render(camera_pose((0.0, 0.0, 3.0), 0.0, math.radians(-60), 0.0), PinholeCamera(64, 64, 90.0))
    px = out.rgb[out.depth_m > 0].astype(float)
    assert len(px) > 1000
    g = px.mean(axis=0)
    assert g[1] > g[0] + 60 and g[1] > g[2] + 40, f"mean colour {g} is not green"


def _object_view(scene, size=128):
    """A view of the object from 2 m away, level with its middle, facing it."""
    lo, hi = scene.bounds_m
    c = (lo + hi) / 2
    dist = 2.0 * float(np.linalg.norm(hi - lo))
    eye = c + np.array([-dist, 0.0, 0.0])
    pose = camera_pose(eye, 0.0, 0.0, 0.0)
    return SceneRenderer(scene).render(pose, PinholeCamera(size, size, 40.0))


@pytest.mark.parametrize("name", ["chair.glb", "fridge_body.glb"])
def test_textured_objects_show_their_texture_colours(assets, name):
    scene = load_scene(str(assets / name))
    assert scene.texture is not None
    out = _object_view(scene)
    obj = out.depth_m > 0
    assert obj.mean() > 0.05
    rendered = out.rgb[obj].astype(float).mean(axis=0)
    # The texture image and the UVs, from the glTF itself (open3d, not through our loader).
    model = o3d.io.read_triangle_model(str(assets / name))
    textured = [(m.mesh, np.asarray(model.materials[m.material_idx].albedo_img)[..., :3])
                for m in model.meshes if model.materials[m.material_idx].albedo_img is not None]
    tex_mean = np.mean([img.reshape(-1, 3).mean(axis=0) for _, img in textured], axis=0)
    assert np.abs(rendered - tex_mean).max() < 30, f"rendered {rendered.round(1)} vs texture {tex_mean.round(1)}"
    # Sharper: the texels the mesh's UVs actually use (a fridge body is the grey part of its atlas).
    used, area = [], []
    for mesh, img in textured:
        uv = np.asarray(mesh.triangle_uvs).reshape(-1, 3, 2).mean(axis=1)
        h, w = img.shape[:2]
        used.append(img[np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1), np.clip((uv[:, 0] * w).astype(int), 0, w - 1)])
        v = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)]
        area.append(np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1))
    used_mean = np.average(np.concatenate(used).astype(float), axis=0, weights=np.concatenate(area))
    assert np.abs(rendered - used_mean).max() < 12, f"rendered {rendered.round(1)} vs texels under the UVs {used_mean.round(1)}"
    # ...and not the flat 0.7 grey (178.5) an untextured load gives.
    assert np.abs(rendered - 0.7 * 255).max() > 8


def test_chair_texture_not_grey(assets):
    out = _object_view(load_scene(str(assets / "chair.glb")))
    m = out.rgb[out.depth_m > 0].astype(float).mean(axis=0)
    assert m[0] > m[2] + 40, f"the chair is brown (red > blue), got {m.round(1)}"


def test_r2r_ce_episode_in_habitat_coordinates_lands_on_stage_floor1(assets, tmp_path):
    """An R2R-CE record written by hand in Habitat's y-up frame: Habitat's stage (y-up, scale 2)
    puts the floor at Habitat y = 2 * file y, so the start must land on our walkable floor."""
    scene_path = assets / "stage_floor1.glb"
    raw = o3d.io.read_triangle_model(str(scene_path)).meshes[0].mesh
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(raw))

    def habitat_floor(x_h, z_h):
        # Straight down in the file's own frame (y up), then Habitat's scale of 2.
        t = rc.cast_rays(o3d.core.Tensor([[x_h / 2, 10.0, z_h / 2, 0.0, -1.0, 0.0]], dtype=o3d.core.float32))["t_hit"].numpy()[0]
        return [x_h, 2 * (10.0 - float(t)), z_h]

    start, goal = habitat_floor(-3.0, 4.0), habitat_floor(5.0, -6.0)
    ep = {
        "episode_id": 1, "trajectory_id": 1, "scene_id": scene_path.name, "start_position": start,
        "start_rotation": [0.0, 0.0, 0.0, 1.0], "info": {"geodesic_distance": 0.0},
        "goals": [{"position": goal, "radius": 3.0}],
        "instruction": {"instruction_text": "Walk across the green floor.", "instruction_tokens": []},
        "reference_path": [start, goal],
    }
    path = write_episodes(EpisodeDataset([Episode(ep)]), tmp_path / "ep.json.gz")
    episode = read_episodes(path).episodes[0]
    # A 40 x 40 m stage: a 0.1 m grid keeps the test quick and is still finer than the 0.25 m steps.
    robot = SimRobot(SimConfig(scene=episode.scene_path(assets), camera={"width_px": 16, "height_px": 16}, nav_cell_m=0.1))
    s = episode.start_pose.xyz
    assert robot.nav.is_navigable(s), f"start {s} is not on walkable ground"
    node = robot.nav.nodes_m[robot.nav.nearest_node(s)]
    assert abs(node[2] - s[2]) < 0.1 and np.hypot(*(node[:2] - s[:2])) < 0.1
    d = robot.geodesic_distance(s, episode.goal_m)
    assert np.isfinite(d) and d >= np.linalg.norm(episode.goal_m[:2] - s[:2]) - 0.1
    robot.reset(episode.start_pose)
    assert np.allclose(robot.true_pose.xyz[:2], s[:2], atol=1e-6) and abs(robot.true_pose.xyz[2] - s[2]) < 0.1


def test_stage_config_beside_the_file_is_what_decides(assets, tmp_path):
    """The same glb copied without its config is read by the rule table (glTF y-up, scale 1)."""
    bare = tmp_path / "stage_floor1.glb"
    bare.write_bytes((assets / "stage_floor1.glb").read_bytes())
    lo, hi = load_scene(str(bare)).bounds_m
    assert hi[0] - lo[0] == pytest.approx(20.0, abs=0.01)
    (tmp_path / "stage_floor1.stage_config.json").write_text(json.dumps({"render_asset": "stage_floor1.glb", "scale": [3, 3, 3]}))
    lo, hi = load_scene(str(bare)).bounds_m
    assert hi[0] - lo[0] == pytest.approx(60.0, abs=0.01)
    # An explicit option in the spec beats the config beside the file.
    lo, hi = load_scene(f"{bare}:scale=0.5").bounds_m
    assert hi[0] - lo[0] == pytest.approx(10.0, abs=0.01)


def test_pictures_of_a_real_asset(assets, tmp_path):
    from services.robot_io.tools.pictures import main

    assert main(["--scene", str(assets / "chair.glb"), "--out", str(tmp_path), "--size", "64"]) == 0
    pano = cv2.imread(str(tmp_path / "panorama.png"))
    assert pano is not None and pano.std() > 5
    assert list(tmp_path.glob("top_view*.png"))


@pytest.mark.parametrize("name", ["simple_room.glb", "stage_floor1.glb", "chair.glb", "fridge_body.glb"])
def test_own_gltf_reader_agrees_with_open3d(assets, name):
    """Our numpy glTF reader (fast on big scans) sees the same surface as open3d's assimp reader."""
    from libs.world.scene_files import read_mesh_file

    ours = read_mesh_file(assets / name)
    model = o3d.io.read_triangle_model(str(assets / name))
    theirs_v = np.concatenate([np.asarray(m.mesh.vertices) for m in model.meshes])
    theirs_t = [np.asarray(m.mesh.vertices)[np.asarray(m.mesh.triangles)] for m in model.meshes]

    def area(tri):
        return float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum() / 2)

    assert len(ours.triangles) == sum(len(t) for t in theirs_t)
    assert area(ours.vertices[ours.triangles]) == pytest.approx(sum(area(t) for t in theirs_t), rel=1e-5)
    assert ours.vertices.min(axis=0) == pytest.approx(theirs_v.min(axis=0), abs=1e-5)
    assert ours.vertices.max(axis=0) == pytest.approx(theirs_v.max(axis=0), abs=1e-5)
