"""The renderer's ray construction and per-pixel shading (compiled kernel and numpy agree bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest

from services.robot_io.core import shading
from services.robot_io.core.render import Intrinsics, SceneRenderer
from libs.world.scene import Scene, Texture
from shared.geometry import PinholeCamera, camera_pose, panorama_headings

RED, GREEN, BLUE, WHITE = (230, 20, 20), (20, 200, 30), (25, 40, 220), (250, 250, 250)


def _wall_scene(textured: bool) -> Scene:
    """A 2 x 2 m wall at x = 2 (facing the origin), two triangles with different vertex colours."""
    v = np.array([[2.0, 1.0, 1.0], [2.0, -1.0, 1.0], [2.0, 1.0, -1.0], [2.0, -1.0, -1.0]])
    t = np.array([[0, 2, 1], [1, 2, 3]])
    cols = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]], np.float32)
    tex = None
    if textured:
        # Top-left corner of the wall (as the camera sees it) has uv (0, 1): image row 0, column 0.
        uv_of = {0: (0.0, 1.0), 1: (1.0, 1.0), 2: (0.0, 0.0), 3: (1.0, 0.0)}
        uvs = np.array([[uv_of[i] for i in tri] for tri in t], np.float32)
        img = np.array([[RED, GREEN], [BLUE, WHITE]], np.uint8)
        tex = Texture(uvs, np.array([0, -1], np.int32), [img])
    return Scene("wall", v, t, cols, np.array([4, 7], np.int32), label_names={4: "a", 7: "b"}, texture=tex)


def _renderers(scene: Scene) -> tuple[SceneRenderer, SceneRenderer]:
    return SceneRenderer(scene, use_kernel=True), SceneRenderer(scene, use_kernel=False)


@pytest.mark.parametrize("textured", [False, True])
def test_wall_depth_colour_labels_and_misses(textured):
    scene = _wall_scene(textured)
    cam = PinholeCamera(64, 48, 90.0)
    pose = camera_pose((0.0, 0.0, 0.0), 0.0, 0.0, camera_height_m=0.0)
    outs = [r.render(pose, cam) for r in _renderers(scene)]
    for out in outs:
        hit = out.depth_m > 0
        # z-depth of a fronto-parallel wall is its distance everywhere it is seen.
        assert np.allclose(out.depth_m[hit], 2.0, atol=1e-5)
        # f = 32 px: the 2 x 2 m wall at 2 m spans 32 px around the principal point (31.5, 23.5).
        assert hit[9:39, 17:47].all() and not hit[:, :15].any() and not hit[:, 49:].any()
        assert not hit[:7].any() and not hit[41:].any()
        assert set(np.unique(out.semantic[hit])) == {4, 7} and np.all(out.semantic[~hit] == -1)
        assert np.all(out.rgb[~hit] == 0)
        if textured:
            # Triangle 0 (upper left of the diagonal) samples the texture; triangle 1 has no
            # material and falls back to its vertex colours (white corner at the bottom right).
            assert tuple(out.rgb[17, 20]) == RED and tuple(out.rgb[9, 40]) == GREEN
            assert tuple(out.rgb[38, 46]) != WHITE and out.rgb[38, 46].min() > 170
        else:
            # Near a corner the blend is that corner's vertex colour.
            assert np.abs(out.rgb[9, 17].astype(int) - (255, 0, 0)).max() <= 32
    assert all(np.array_equal(getattr(outs[0], f), getattr(outs[1], f)) for f in ("rgb", "depth_m", "semantic"))


def test_blend_matches_float64_barycentric_reference():
    scene = _wall_scene(False)
    r = SceneRenderer(scene)
    k = Intrinsics(20.0, 20.0, 15.5, 11.5, 32, 24)
    pose = camera_pose((0.0, 0.0, 0.0), 0.1, 0.05, camera_height_m=0.0)
    out = r.render(pose, k)
    rays = np.stack(np.meshgrid((np.arange(32) - 15.5) / 20.0, (np.arange(24) - 11.5) / 20.0), -1)
    d = np.concatenate([rays, np.ones((24, 32, 1))], -1) @ pose[:3, :3].T
    hit = r.cast(np.broadcast_to(pose[:3, 3], d.shape), d)
    ok = hit["primitive_ids"] != np.uint32(0xFFFFFFFF)
    tri = scene.triangles[hit["primitive_ids"][ok]]
    w = hit["primitive_uvs"][ok].astype(np.float64)
    bary = np.column_stack([1 - w.sum(1), w[:, 0], w[:, 1]])
    ref = np.einsum("nk,nkc->nc", bary, scene.vertex_colors[tri].astype(np.float64)) * 255
    assert np.abs(out.rgb[ok].astype(float) - ref).max() <= 1.0


@pytest.mark.skipif(not shading.AVAILABLE, reason="numba not installed")
def test_kernel_equals_numpy_on_a_generated_panorama(house_robot):
    scene = house_robot.scene
    fast, slow = _renderers(scene)
    cam = PinholeCamera(48, 40, 90.0)
    heads = panorama_headings(0.7, 12)
    a = fast.render_views(scene.start_pose.xyz, heads, cam)
    b = slow.render_views(scene.start_pose.xyz, heads, cam)
    for f in ("rgb", "depth_m", "semantic"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    # The rays come from the shared camera model: view 0's pixel rays, rotated, at unit z.
    pose = camera_pose(scene.start_pose.xyz, heads[0], 0.0, 1.25)
    rays = cam.pixel_rays() @ pose[:3, :3].T
    t = fast.first_hit_distance(np.broadcast_to(pose[:3, 3], rays.shape), rays)
    assert np.allclose(a.depth_m[0], np.where(np.isfinite(t), t, 0.0), rtol=1e-5, atol=1e-5)


@pytest.mark.skipif(not shading.AVAILABLE, reason="numba not installed")
def test_compiled_rays_equal_the_numpy_sums():
    from services.robot_io.core.render import _homogeneous_rays, ray_matrices, write_rays

    rng = np.random.default_rng(5)
    k = Intrinsics(37.0, 41.5, 20.3, 15.9, 44, 30)  # non-square pixels, off-centre principal point
    poses = np.stack([camera_pose(rng.uniform(-50, 50, 3), h, p, 1.25)
                      for h, p in zip(rng.uniform(-np.pi, np.pi, 7), rng.uniform(-0.8, 0.8, 7))])
    mats = ray_matrices(poses)
    fast, slow = (np.empty((7, 44 * 30, 6), np.float32) for _ in range(2))
    write_rays(_homogeneous_rays(k), mats, fast, use_kernel=True)
    write_rays(_homogeneous_rays(k), mats, slow, use_kernel=False)
    assert fast.tobytes() == slow.tobytes()
    # Origins are the camera centres exactly; directions the rotated unit-z pixel rays.
    assert np.array_equal(fast[:, :, :3], np.broadcast_to(poses[:, None, :3, 3].astype(np.float32), fast[:, :, :3].shape))
    ref = np.einsum("nk,bjk->bnj", _homogeneous_rays(k)[:, :3].astype(np.float64), poses[:, :3, :3])
    assert np.allclose(fast[:, :, 3:], ref, atol=1e-5)
