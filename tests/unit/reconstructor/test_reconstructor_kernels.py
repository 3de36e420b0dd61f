"""Compiled fusion and outlier search (numba) against the array code and open3d, exactly."""

from __future__ import annotations

import numpy as np
from shared.o3d import o3d
import pytest

from services.reconstructor.core import RECONSTRUCTORS, BackendUnavailableError, InputError, RegionInput, kernels
from services.reconstructor.core.frames import PosedImage
from services.reconstructor.core.regional import statistical_inliers
from services.reconstructor.core.voxel import _reduce_dense
from shared.geometry import PinholeCamera, camera_pose
from shared.schemas import Pose

needs_numba = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")


def _region(n_frames: int = 7, seed: int = 0, w: int = 40, h: int = 30, far: bool = False) -> RegionInput:
    """Frames of random depth (with holes, NaN, too near/far pixels) and labels (several per voxel)."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(w, h, 90.0)
    images = []
    for i in range(n_frames):
        depth = rng.uniform(0.05, 9.0, (h, w)).astype(np.float32)
        depth[rng.random((h, w)) < 0.1] = 0.0
        depth[rng.random((h, w)) < 0.02] = np.nan
        # Smooth patches too, so that neighbouring pixels share voxels (the kernel's caches).
        depth[: h // 2, : w // 2] = np.float32(1.5 + 0.01 * i)
        sem = rng.integers(-1, 4, (h, w)).astype(np.int32)
        sem[rng.random((h, w)) < 0.01] = 70000  # beyond the packable labels: ignored by both paths
        pos = rng.uniform(-2, 2, 3) + ([1e4, 0, 0] if far else 0)
        images.append(PosedImage(
            rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            world_from_camera=camera_pose(pos, rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3), 1.25),
            camera=cam, depth_m=depth, semantic=sem, index=i,
        ))
    return RegionInput(0, Pose(position_m=(0.3, -0.2, 0.0), heading_rad=0.4), images)


@needs_numba
@pytest.mark.parametrize("stride,batch,voxel", [(1, 3, 0.1), (2, 32, 0.05), (1, 1, 0.5)])
def test_compiled_fusion_equals_array_fusion_bit_for_bit(stride, batch, voxel):
    region = _region()
    cfg = {"pixel_stride": stride, "batch_frames": batch, "voxel_m": voxel, "remove_outliers": False}
    compiled = RECONSTRUCTORS.create("rgbd", {**cfg, "kernel": "numba", "threads": 2})
    array = RECONSTRUCTORS.create("rgbd", {**cfg, "kernel": "numpy"})
    assert compiled.kernel == "numba" and array.kernel == "numpy"
    a, b = compiled.reconstruct(region), array.reconstruct(region)
    assert a.points_in == b.points_in > 0
    assert len(a.cloud) == len(b.cloud) > 10
    assert np.array_equal(a.cloud.xyz, b.cloud.xyz)
    assert np.array_equal(a.cloud.rgb, b.cloud.rgb)
    assert np.array_equal(a.cloud.labels, b.cloud.labels)
    assert (a.cloud.labels >= 0).any()
    assert a.cloud.view_dirs is not None and np.array_equal(a.cloud.view_dirs, b.cloud.view_dirs)


@needs_numba
@pytest.mark.parametrize("stride,voxel", [(1, 0.1), (2, 0.05), (1, 0.5)])
def test_compiled_and_array_voxel_sums_are_bit_identical(stride, voxel):
    # The sums themselves, view vectors included, not the int8 directions they end as (those would hide
    # a last-bit difference).
    region = _region(5, seed=4)
    local = region.local_from_world()
    backend = RECONSTRUCTORS.create("rgbd", {"pixel_stride": stride, "voxel_m": voxel, "kernel": "numba"})
    [(fused, _, _)] = backend._fuse_compiled(region.images, local, True)
    [(xyz, rgb, lab, views)] = backend._backproject(region.images, local, True)
    reduced, _ = _reduce_dense(xyz, rgb, lab, voxel, views)
    assert len(fused[0]) == len(reduced[0]) > 100
    for got, want in zip(fused, reduced, strict=True):
        assert np.array_equal(got, want)
    # Unit vectors: a voxel's sum is at most its count long, and exactly 1 for a single point.
    length = np.linalg.norm(fused[4], axis=1)
    assert (length <= fused[3] * (1 + 1e-6)).all()
    single = fused[3] == 1
    assert single.any() and np.allclose(length[single], 1.0, atol=1e-6)


@needs_numba
def test_compiled_fusion_result_does_not_depend_on_threads():
    region = _region(9, seed=3)
    one = RECONSTRUCTORS.create("rgbd", {"threads": 1, "batch_frames": 2}).reconstruct(region).cloud
    two = RECONSTRUCTORS.create("rgbd", {"threads": 2, "batch_frames": 2}).reconstruct(region).cloud
    assert np.array_equal(one.xyz, two.xyz) and np.array_equal(one.labels, two.labels)
    assert np.array_equal(one.view_dirs, two.view_dirs)


@needs_numba
def test_frame_fuser_grows_its_tables_and_counts_every_point():
    # A tiny initial capacity forces the tables to grow within one batch; coarse voxels mix labels.
    region = _region(4, seed=5, w=64, h=48)
    local = region.local_from_world()
    rays, backs = RECONSTRUCTORS.create("rgbd", {})._pixel_rays(region.images[0].camera)
    f = kernels.FrameFuser(0.2, 0.1, 8.0, True, capacity=16)
    for im in region.images:
        assert f.add(im.depth_m, im.rgb, im.semantic, np.ascontiguousarray((local @ im.world_from_camera)[:3],
                     np.float32), rays, backs, 1)
    (keys, sxyz, srgb, cnt, _), (vk, vc) = f.result()
    valid = sum(int(((im.depth_m > np.float32(0.1)) & (im.depth_m < np.float32(8.0))).sum()) for im in region.images)
    assert f.points == valid == int(cnt.sum())
    assert np.all(np.diff(keys) > 0) and np.all(np.diff(vk) > 0)
    voted = vk >> kernels.LABEL_BITS
    assert np.isin(voted, keys).all()
    assert (np.diff(voted) == 0).any()  # some voxels hold several labels (the overflow table)
    labelled = sum(int(((im.semantic >= 0) & (im.semantic <= kernels.LABEL_MAX)
                        & (im.depth_m > np.float32(0.1)) & (im.depth_m < np.float32(8.0))).sum())
                   for im in region.images)
    assert int(vc.sum()) == labelled


@needs_numba
def test_points_out_of_range_raise_in_both_paths():
    region = _region(2, far=True)
    for kernel in ("numba", "numpy"):
        with pytest.raises(InputError, match="span more than"):
            RECONSTRUCTORS.create("rgbd", {"kernel": kernel, "voxel_m": 0.01}).reconstruct(region)


def test_numba_kernel_requested_without_numba(monkeypatch):
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    with pytest.raises(BackendUnavailableError):
        RECONSTRUCTORS.create("rgbd", {"kernel": "numba"})
    assert RECONSTRUCTORS.create("rgbd", {}).kernel == "numpy"


def _o3d_inliers(xyz: np.ndarray, k: int, ratio: float) -> np.ndarray:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz.astype(np.float64)))
    _, keep = pcd.remove_statistical_outlier(nb_neighbors=k, std_ratio=ratio)
    return np.sort(np.asarray(keep, np.int64))


@needs_numba
@pytest.mark.parametrize("cell_m,threads", [(0.03, 1), (0.03, 2), (0.2, 2), (0.004, 1)])
def test_grid_outlier_search_keeps_what_open3d_keeps(cell_m, threads):
    rng = np.random.default_rng(7)
    # A voxelised room-like cloud (planes), scattered outliers and a duplicated point (mean 0).
    g = np.arange(0, 2.0, 0.03)
    u, v = np.meshgrid(g, g)
    planes = [np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1),
              np.stack([u.ravel(), np.zeros(u.size), v.ravel()], 1)]
    xyz = np.concatenate(planes + [rng.uniform(-1, 3, (300, 3))])
    xyz += rng.normal(0, 0.003, xyz.shape)
    xyz = np.concatenate([xyz, xyz[:1]])
    mine = statistical_inliers(xyz, 16, 2.0, cell_m, threads)
    assert np.array_equal(mine, _o3d_inliers(xyz, 16, 2.0))
    assert 0 < len(xyz) - len(mine) < 400


@needs_numba
def test_knn_mean_distances_are_exact():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(2)
    xyz = np.concatenate([rng.uniform(0, 1, (2000, 3)), rng.uniform(5, 6, (10, 3))])
    want = cKDTree(xyz).query(xyz, k=8)[0].mean(axis=1)
    got = kernels.knn_mean_distances(xyz, 8, 0.05, threads=2, max_cells=1000)  # coarser cells forced
    assert np.allclose(got, want, rtol=1e-12, atol=0)
    few = kernels.knn_mean_distances(xyz[:5], 8, 0.05)  # fewer points than k: all of them
    assert np.allclose(few, cKDTree(xyz[:5]).query(xyz[:5], k=5)[0].mean(axis=1))


@needs_numba
def test_knn_cells_capped_per_point_give_the_same_bits():
    # Scattered far points stretch the bounding box: at 5 cm cells it needs 1.6e6 cells, 765 per point,
    # and the default caps it at 8 per point (cells 5 times as wide). The same means to the bit.
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(4)
    xyz = np.concatenate([rng.uniform(0, 1, (2000, 3)), rng.uniform(-1, 5, (40, 3))])
    fine = kernels.knn_mean_distances(xyz, 8, 0.05, cells_per_point=10**6)
    capped = kernels.knn_mean_distances(xyz, 8, 0.05)
    assert np.array_equal(fine, capped)
    assert np.allclose(capped, cKDTree(xyz).query(xyz, k=8)[0].mean(axis=1), rtol=1e-12, atol=0)


@pytest.mark.parametrize("kernel", [pytest.param("numba", marks=needs_numba), "numpy"])
def test_a_frame_that_declares_depth_noise_is_fused_only_as_far_as_it_is_good(kernel):
    # sigma = rel * z^2 reaches max_depth_noise_m (4 cm) at 2 m for rel 0.01: the frames' depth past 2 m
    # is left out (samples scattered ~10 cm at 3 m smear a wall a nearer look mapped cleanly); an exact
    # sensor (rel 0) keeps max_depth_m. Both paths agree bit for bit, as without noise.
    region = _region(5, seed=2)
    # Raw depth (not denoised): its sigma is the declared one (denoised frames: test_depth_denoise.py).
    cfg = {"fusion": "voxels", "kernel": kernel, "remove_outliers": False, "pixel_stride": 1,
           "denoise_window_px": 1}
    rgbd = RECONSTRUCTORS.create("rgbd", cfg)
    exact = rgbd.reconstruct(region)
    for im in region.images:
        im.depth_noise_rel = 0.01
    assert rgbd.depth_limit_m(region.images[0]) == pytest.approx(2.0)
    noisy = rgbd.reconstruct(region)
    valid = [np.count_nonzero((im.depth_m > 0.1) & (im.depth_m < lim)) for im in region.images for lim in (2.0, 8.0)]
    assert noisy.points_in == sum(valid[0::2]) < exact.points_in == sum(valid[1::2])
    local = region.local_from_world()
    cams = np.array([(local @ im.world_from_camera)[:3, 3] for im in region.images])
    reach = np.linalg.norm(noisy.cloud.xyz[:, None, :] - cams[None], axis=2).min(axis=1)
    assert reach.max() < 2.0 * np.sqrt(3) + 0.1  # the corner ray of a 90 deg view at z = 2 m
    if kernel == "numba":
        array = RECONSTRUCTORS.create("rgbd", {**cfg, "kernel": "numpy"}).reconstruct(region)
        assert np.array_equal(array.cloud.xyz, noisy.cloud.xyz)
        assert np.array_equal(array.cloud.labels, noisy.cloud.labels)


def test_frames_carry_their_sensors_depth_noise_from_the_robot_to_the_reconstructor():
    from services.reconstructor.core.frames import posed_from_frame
    from services.robot_io.core import ROBOTS

    robot = ROBOTS.create("sim", {"scene": "generated:3:area=50", "camera": {"width_px": 32, "height_px": 32},
                                  "noise": {"depth_noise_rel": 0.02}})
    try:
        frame = robot.render_frame()
        assert frame.depth_noise_rel == 0.02 and posed_from_frame(frame).depth_noise_rel == 0.02
    finally:
        robot.close()
