"""Anticipated views: geometry, occlusion, holes, labels, backends, culling, fidelity.

Tests of the paper's fixed 3x3 splat ask for ``mode: paper``; the visibility mode (the default)
has its own tests in test_renderer_visibility.py and shares the rest."""

from __future__ import annotations

import math

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from services.renderer.tools import scenes
from shared.cloud import EmptyCloudError, PointCloud
from shared.geometry import PinholeCamera, camera_pose
from libs.pointrender import RENDERERS, IndexedCloud, kernels
from libs.pointrender.cloud import Frustum
from libs.pointrender.errors import BackendUnavailableError
from shared.schemas import CameraIntrinsics, ViewPose

CAM = PinholeCamera(256, 256, 90.0)
PAPER = {"mode": "paper"}
MODES = ["visibility", "paper"]


def _wall(x_m: float, half_m: float, n: int, colour, label: int, seed: int = 0) -> PointCloud:
    """A dense vertical square facing -x at distance ``x_m`` in front of a camera at (0, 0, 1.25)."""
    rng = np.random.default_rng(seed)
    yz = rng.uniform(-half_m, half_m, size=(n, 2))
    xyz = np.column_stack([np.full(n, x_m), yz[:, 0], 1.25 + yz[:, 1]])
    return PointCloud(xyz, np.tile(np.array(colour, np.uint8), (n, 1)), np.full(n, label, np.int32),
                      {0: "near", 1: "far"})


def _view(heading=0.0, pitch=0.0, pos=(0.0, 0.0, 0.0)):
    return ViewPose(position_m=pos, heading_rad=heading, pitch_rad=pitch)


@pytest.mark.parametrize("hfov_deg", [60.0, 90.0, 120.0])
@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_point_at_known_angle_lands_on_expected_pixel(hfov_deg, backend):
    cam = PinholeCamera(256, 256, hfov_deg)
    # A tiny cluster 20 deg to the left and 10 deg up, 3 m ahead (heading 0 looks along +x).
    az, el, d = math.radians(20.0), math.radians(10.0), 3.0
    centre = np.array([d, d * math.tan(az), 1.25 + d * math.tan(el)])
    pts = centre + np.random.default_rng(0).normal(0, 1e-4, size=(50, 3))
    index = IndexedCloud(PointCloud(pts, np.full((50, 3), 200, np.uint8)))
    out = RENDERERS.create(backend, {"lod_points_per_px": None, **PAPER}).render(index, [_view()], cam)
    filled = np.argwhere(~out.hole_mask[0])
    # Expected pixel from the angles alone: left of centre is smaller u, up is smaller v.
    u = cam.cx - cam.fx * math.tan(az)
    v = cam.cy - cam.fy * math.tan(el)
    assert len(filled) == 9  # one splat: the 3x3 pixels around the point
    row, col = filled.mean(axis=0)
    assert abs(col - round(u)) < 1e-9 and abs(row - round(v)) < 1e-9
    assert np.allclose(out.depth_m[0][~out.hole_mask[0]], d, atol=1e-3)


@pytest.fixture(scope="module")
def near_and_far_walls() -> IndexedCloud:
    """One index for both modes: the renderer caches what each mode derives from it under its own
    key, and what they share (the points' spacing) is computed once for the 412,800 points. The far
    wall (5,000 points per m^2: ~5 a pixel at 4 m) reaches 0.2 m past the 90-degree view's +-4 m
    there, so it fills every corner of the image; a wider wall only adds points no view draws."""
    near = _wall(2.0, 0.6, 60_000, (250, 0, 0), 0)
    far = _wall(4.0, 4.2, 352_800, (0, 0, 250), 1, seed=1)
    return IndexedCloud(PointCloud.concatenate([near, far]))


@pytest.mark.parametrize("mode", MODES)
def test_near_wall_hides_far_wall(near_and_far_walls, mode):
    out = RENDERERS.create("numpy", {"mode": mode}).render(near_and_far_walls, [_view()], CAM)
    rgb, depth, labels = out.rgb[0], out.depth_m[0], out.labels[0]
    # The near wall spans atan(0.6/2) = 16.7 deg either side: pixels within +-0.3 * fx of centre.
    c = int(CAM.cx)
    inner = slice(c - 25, c + 25)
    assert (rgb[inner, inner, 0] > 240).all() and (rgb[inner, inner, 2] < 10).all()
    assert np.allclose(depth[inner, inner], 2.0, atol=0.02)
    assert (labels[inner, inner] == 0).all()
    # Outside the near wall, the far wall shows.
    assert (rgb[5:20, 5:20, 2] > 240).all() and np.allclose(depth[5:20, 5:20], 4.0, atol=0.05)
    assert (labels[5:20, 5:20] == 1).all()


@pytest.mark.parametrize("mode", MODES)
def test_hole_mask_marks_pixels_no_point_reached(mode):
    wall = _wall(3.0, 0.5, 50_000, (100, 150, 200), 0)
    out = RENDERERS.create("numpy", {"mode": mode}).render(IndexedCloud(wall), [_view()], CAM)
    hole, depth, rgb = out.hole_mask[0], out.depth_m[0], out.rgb[0]
    half_px = 0.5 / 3.0 * CAM.fx
    c = CAM.cx
    assert not hole[int(c - half_px) + 3 : int(c + half_px) - 3, int(c - half_px) + 3 : int(c + half_px) - 3].any()
    assert hole[:20].all() and hole[:, :20].all()
    assert (depth[hole] == 0).all() and (rgb[hole] == 0).all() and (out.labels[0][hole] == -1).all()
    assert (depth[~hole] > 0).all()
    assert 0.0 < out.hole_fraction < 1.0


@pytest.mark.parametrize("mode", MODES)
def test_labels_take_the_nearest_point_without_blending(mode):
    # Interleaved labels on the same plane, 1 cm apart in depth: the nearer one wins everywhere.
    near = _wall(3.0, 1.0, 80_000, (0, 255, 0), 0)
    behind = _wall(3.01, 1.0, 80_000, (255, 0, 255), 1, seed=3)
    # Every point drawn: a voxel level of detail (2 px cells at 3 m: 4.7 cm) would merge the two
    # layers into one point per cell before any splat saw them (test_renderer_lod covers that).
    cfg = {"mode": mode, "lod": None}
    out = RENDERERS.create("numpy", cfg).render(IndexedCloud(PointCloud.concatenate([near, behind])), [_view()], CAM)
    filled = ~out.hole_mask[0]
    labels = out.labels[0][filled]
    assert set(np.unique(labels)) <= {0, 1}
    # Colours blend (both layers are within epsilon), labels never do: they are ids, not averages.
    assert (labels == 0).mean() > 0.7
    mid = out.rgb[0][128, 128]
    assert 40 < mid[0] < 215 and 40 < mid[1] < 215


def test_numpy_and_torch_agree_in_paper_mode(room_index):
    views = [_view(h, p, pos) for pos, h, p in scenes.room_view_poses(3, seed=5)]
    for algorithm in ("layered", "exact"):
        a = RENDERERS.create("numpy", {"algorithm": algorithm, **PAPER}).render(room_index, views, CAM)
        b = RENDERERS.create("torch", {"algorithm": algorithm, "device": "cpu", **PAPER}).render(room_index, views, CAM)
        assert np.array_equal(a.hole_mask, b.hole_mask)
        assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 1
        assert np.allclose(a.depth_m, b.depth_m, rtol=1e-4, atol=1e-4)
        assert np.array_equal(a.labels, b.labels)


def test_layered_matches_exact_reference(room_index, room_gt):
    views = [_view(h, p, pos) for pos, h, p in scenes.room_view_poses(4, seed=6)]
    fast = RENDERERS.create("numpy", PAPER).render(room_index, views, CAM)
    ref = RENDERERS.create("numpy", {"algorithm": "exact", **PAPER}).render(room_index, views, CAM)
    assert np.array_equal(fast.hole_mask, ref.hole_mask)
    assert np.array_equal(fast.labels, ref.labels)
    # The two differ only at silhouettes; measured PSNR between them is ~35 dB.
    assert peak_signal_noise_ratio(ref.rgb, fast.rgb) > 30.0
    assert np.median(np.abs(fast.depth_m - ref.depth_m)) < 1e-3


@pytest.mark.parametrize("mode", MODES)
def test_culling_and_lod_off_give_the_same_image_as_culling(room_index, mode):
    views = [_view(h, p, pos) for pos, h, p in scenes.room_view_poses(3, seed=7)]
    cfg = {"lod_points_per_px": None, "mode": mode}
    culled = RENDERERS.create("numpy", cfg).render(room_index, views, CAM)
    full = RENDERERS.create("numpy", {**cfg, "cull": False}).render(room_index, views, CAM)
    assert all(c < len(room_index) for c in culled.visible_points)
    assert np.array_equal(culled.rgb, full.rgb)
    assert np.array_equal(culled.depth_m, full.depth_m)
    assert np.array_equal(culled.labels, full.labels)


@pytest.mark.parametrize("hfov_deg", [60.0, 90.0, 120.0])
def test_paper_fidelity_against_ray_cast_ground_truth(room_index, room_gt, hfov_deg):
    # Measured on this 1e6-point cloud of the flat: mean SSIM 0.66 / 0.79 / 0.76 at HFOV 60 / 90 /
    # 120 (one view 1.5 m from a wall at HFOV 60 drops to 0.31: 0.1 points per pixel leave the 3x3
    # splat with 11% holes and let the far wall show through), PSNR ~20-22 dB. The thresholds sit
    # below those with margin for sampling seeds; a projection or occlusion bug gives SSIM < 0.3.
    cam = PinholeCamera(256, 256, hfov_deg)
    poses = scenes.room_view_poses(4, seed=8)
    out = RENDERERS.create("numpy", PAPER).render(room_index, [_view(h, p, pos) for pos, h, p in poses], cam)
    ssim, psnr, label_ok = [], [], []
    for i, (pos, h, p) in enumerate(poses):
        rgb, depth, labels = room_gt.render(camera_pose(pos, h, p), cam)
        ssim.append(structural_similarity(rgb, out.rgb[i], channel_axis=2))
        psnr.append(peak_signal_noise_ratio(rgb, out.rgb[i]))
        seen = ~out.hole_mask[i]
        label_ok.append((out.labels[i][seen] == labels[seen]).mean())
        assert np.median(np.abs(out.depth_m[i][seen] - depth[seen])) < 0.02
    assert np.mean(ssim) > 0.55, ssim
    assert np.mean(psnr) > 18.0, psnr
    assert np.mean(label_ok) > 0.93, label_ok
    assert out.hole_fraction < 0.05


def test_batch_equals_single_views(room_index):
    views = [_view(h, p, pos) for pos, h, p in scenes.room_view_poses(3, seed=9)]
    r = RENDERERS.create("numpy")
    batch = r.render(room_index, views, CameraIntrinsics())
    for i, v in enumerate(views):
        one = r.render(room_index, [v], CameraIntrinsics())
        assert np.array_equal(one.rgb[0], batch.rgb[i])
    assert len(batch.view_s) == 3 and batch.rgb.shape == (3, 256, 256, 3)


def test_cloud_without_labels_and_empty_view():
    wall = _wall(3.0, 0.5, 1000, (1, 2, 3), 0)
    cloud = PointCloud(wall.xyz, wall.rgb)
    out = RENDERERS.create("numpy").render(IndexedCloud(cloud), [_view(math.pi)], CAM)  # looking away
    assert out.labels is None and out.hole_mask.all() and (out.depth_m == 0).all()


def test_errors():
    with pytest.raises(EmptyCloudError):
        IndexedCloud(PointCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8)))
    with pytest.raises(ValueError):
        RENDERERS.create("numpy", {"near_m": 5.0, "far_m": 1.0})
    with pytest.raises(Exception):
        RENDERERS.create("numpy", {"kernel_size": 5})  # unknown fields are refused
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(BackendUnavailableError):
            RENDERERS.create("torch", {"device": "cuda"})


def test_ply_round_trip_keeps_labels(tmp_path):
    cloud = _wall(3.0, 0.5, 500, (10, 20, 30), 1)
    cloud.save(tmp_path / "c.ply")
    back = PointCloud.load(tmp_path / "c.ply")
    assert np.allclose(back.xyz, cloud.xyz, atol=1e-6)
    assert np.array_equal(back.rgb, cloud.rgb)
    assert np.array_equal(back.labels, cloud.labels) and back.label_names == cloud.label_names


def test_replica_office_fidelity(shared_data):
    mesh = scenes.replica_office(shared_data)
    # 250k points: SSIM 0.87 (0.90 at 500k, for 2.3x the CPU: the normals of every point), and the
    # same geometry errors fall below the bar as at 500k (hfov 100 for 90: 0.49; the image
    # transposed or mirrored: 0.39).
    index = IndexedCloud(scenes.sample_mesh(mesh, 250_000))
    gt = scenes.RaycastCamera(mesh)
    poses = scenes.replica_view_poses(shared_data, 4, stride=400)
    out = RENDERERS.create("numpy").render_poses(index, poses, CAM)
    ssim = [structural_similarity(gt.render(p, CAM)[0], out.rgb[i], channel_axis=2) for i, p in enumerate(poses)]
    # The smooth office texture is easy for splats away from holes.
    assert np.mean(ssim) > 0.6, ssim


needs_numba = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")


@needs_numba
@pytest.mark.parametrize("mode", [*MODES, "visibility-flat", "visibility-sides"])
@pytest.mark.parametrize("hfov_deg", [60.0, 120.0])
def test_compiled_kernel_is_bit_identical_to_array_code(room_index, room_index_sided, hfov_deg, mode):
    cam = PinholeCamera(200, 150, hfov_deg)  # not square: rows and columns must not be swapped
    poses = [camera_pose(pos, h, p) for pos, h, p in scenes.room_view_poses(4, seed=13)]
    # Standing in a wall: points behind the camera, inside the near plane and at grazing angles.
    poses.append(camera_pose((4.0, 3.0, 0.0), 0.3, 0.0))
    # Outside the flat, facing its corner: empty space around it, so that both paths leave holes
    # (the flat's dense cloud leaves none inside).
    poses.append(camera_pose((-2.0, -2.0, 0.0), math.pi / 4, 0.0))
    # "visibility-flat": the visibility mode without the slope-scaled tolerance (no normals).
    # "visibility-sides": a map that records where its points were seen from (the side test).
    cfg = {"mode": "visibility", "visibility_slope_px": 0.0} if mode == "visibility-flat" else {"mode": mode}
    if mode == "visibility-sides":
        cfg, room_index = {"mode": "visibility"}, room_index_sided
    compiled = RENDERERS.create("numpy", {"kernel": "numba", **cfg})
    array = RENDERERS.create("numpy", {"kernel": "numpy", **cfg})
    assert compiled.kernel == "numba" and array.kernel == "array"
    a = compiled.render_poses(room_index, poses, cam)
    b = array.render_poses(room_index, poses, cam)
    if mode == "visibility-sides":  # the test has unseen sides to draw (in the unknown grey)
        assert ((a.rgb == 128).all(axis=-1) & ~a.hole_mask).mean() > 0.01
    assert np.array_equal(a.rgb, b.rgb)
    assert np.array_equal(a.depth_m, b.depth_m)
    assert np.array_equal(a.hole_mask, b.hole_mask)
    assert np.array_equal(a.labels, b.labels)
    assert a.visible_points == b.visible_points
    assert 0.0 < a.hole_fraction < 0.5


@needs_numba
@pytest.mark.parametrize("mode", MODES)
def test_compiled_kernel_without_labels_and_lod_off(mode):
    near = _wall(2.0, 0.6, 20_000, (250, 0, 0), 0)
    far = _wall(4.0, 3.0, 80_000, (0, 0, 250), 1, seed=1)
    both = PointCloud.concatenate([near, far])
    index = IndexedCloud(PointCloud(both.xyz, both.rgb), block_m=0.5)
    cfg = {"lod_points_per_px": None, "mode": mode}
    a = RENDERERS.create("numpy", {**cfg, "kernel": "numba"}).render(index, [_view(), _view(0.4)], CAM)
    b = RENDERERS.create("numpy", {**cfg, "kernel": "numpy"}).render(index, [_view(), _view(0.4)], CAM)
    assert a.labels is None and b.labels is None
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth_m, b.depth_m)
    assert (a.rgb[0, 128, 128] == (250, 0, 0)).all()


def test_views_on_threads_equal_sequential_views(room_index):
    views = [_view(h, p, pos) for pos, h, p in scenes.room_view_poses(5, seed=14)]
    one = RENDERERS.create("numpy", {"workers": 1}).render(room_index, views, CAM)
    many = RENDERERS.create("numpy", {"workers": 3}).render(room_index, views, CAM)
    assert np.array_equal(one.rgb, many.rgb) and np.array_equal(one.labels, many.labels)
    assert np.array_equal(one.depth_m, many.depth_m)
    assert one.visible_points == many.visible_points
    assert many.batch_s > 0 and len(many.view_s) == 5 and all(t > 0 for t in many.view_s)


def test_numba_kernel_requested_without_numba(monkeypatch):
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    with pytest.raises(BackendUnavailableError):
        RENDERERS.create("numpy", {"kernel": "numba"})
    # "auto" falls back to the array code.
    assert RENDERERS.create("numpy").kernel == "array"


@needs_numba
def test_compiled_frustum_culling_selects_the_blocks_the_array_code_selects(room_index):
    rng = np.random.default_rng(3)
    lo, hi = room_index.cloud.xyz.min(axis=0), room_index.cloud.xyz.max(axis=0)
    selected = 0
    for cam in (PinholeCamera(256, 256, 90.0), PinholeCamera(200, 150, 120.0)):
        frustum = Frustum.for_camera(cam, 0.05, 20.0)
        for _ in range(100):
            pose = camera_pose(rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi), rng.uniform(-0.8, 0.8), 0.0)
            a = room_index.visible_blocks(pose, frustum)
            assert np.array_equal(a, room_index.visible_blocks(pose, frustum, compiled=False))
            selected += int(a.sum())
    assert 0 < selected < 200 * room_index.block_count  # some blocks in view, not all of them
