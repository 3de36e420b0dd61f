"""Depth denoising of frames that declare their noise (issue 33): a noisy wall fused thin, depth edges
kept, holes kept, exact depth untouched, and the compiled loop equal to the array code."""

from __future__ import annotations

import numpy as np
import pytest

from services.reconstructor.core import RECONSTRUCTORS, RegionInput, kernels
from services.reconstructor.core.denoise import denoise_depth
from services.reconstructor.core.frames import PosedImage
from shared.geometry import PinholeCamera, camera_pose
from shared.schemas import Pose

needs_numba = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
REL = 0.01  # bench.anticipation's noisy robot: sigma = 0.01 * z^2


def _noisy(true: np.ndarray, rel: float, seed: int, holes: float = 0.05) -> np.ndarray:
    """The simulator's depth noise (robot_io sensors): Gaussian sigma = rel * z^2, then random holes."""
    rng = np.random.default_rng(seed)
    d = (true + rel * true**2 * rng.standard_normal(true.shape)).astype(np.float32)
    d[rng.random(true.shape) < holes] = 0.0
    return d


def _step(h: int = 48, w: int = 64) -> np.ndarray:
    """A slanted wall at 1.0-1.5 m with a door frame 0.6 m behind it on the right."""
    xx = np.mgrid[0:h, 0:w][1]
    true = (1.0 + 0.5 * xx / w).astype(np.float32)
    true[:, w // 2 :] += 0.6
    return true


@needs_numba
@pytest.mark.parametrize("window", [3, 5, 7])
def test_the_compiled_loop_equals_the_array_code_bit_for_bit(window):
    d = _noisy(_step(), 0.02, seed=window)
    d[5, 7] = np.nan
    d[0, :] = 0.0  # a row of holes at the border
    a = denoise_depth(d, 0.02, window, compiled=False)
    b = denoise_depth(d, 0.02, window, compiled=True)
    assert np.array_equal(a, b, equal_nan=True)
    assert not np.array_equal(a, d, equal_nan=True)  # it did something


@pytest.mark.parametrize("compiled", [pytest.param(True, marks=needs_numba), False])
def test_noise_is_averaged_out_holes_stay_and_the_door_frame_is_not_blended(compiled):
    true = _step()
    d = _noisy(true, REL, seed=1)
    out = denoise_depth(d, REL, 5, compiled=compiled)
    valid = d > 0
    assert np.array_equal(out > 0, valid)  # holes stay holes, no pixel is invented
    sigma = REL * true**2
    raw = np.sqrt(np.mean(((d - true) / sigma)[valid] ** 2))
    den = np.sqrt(np.mean(((out - true) / sigma)[valid] ** 2))
    assert raw == pytest.approx(1.0, abs=0.1) and den < 0.45 * raw
    # Every pixel on its own surface: none pulled into the 0.6 m between the wall and the frame.
    assert np.abs(out - true)[valid].max() < (4.5 * sigma)[valid].max()


def test_a_frame_that_declares_no_noise_is_returned_untouched():
    d = _noisy(_step(), REL, seed=3)
    assert denoise_depth(d, 0.0) is d
    assert denoise_depth(d, REL, window_px=1) is d
    with pytest.raises(ValueError):
        denoise_depth(d, REL, window_px=4)


def _wall_region(rel: float, n_frames: int = 6) -> RegionInput:
    """Frames of a flat wall 1.6 m ahead (world x = 1.6), from slightly different places, noisy depth."""
    cam = PinholeCamera(64, 48, 90.0)
    rays = cam.pixel_rays()
    images = []
    for i in range(n_frames):
        y = 0.05 * i
        wfc = camera_pose(np.array([0.0, y, 0.0]), 0.0, 0.0, 1.25)
        # z-depth of the plane x = 1.6 (the camera looks along +x: camera z is world x)
        true = np.full((48, 64), 1.6, np.float32) / rays[..., 2].astype(np.float32)
        images.append(PosedImage(rgb=np.full((48, 64, 3), 128, np.uint8), world_from_camera=wfc, camera=cam,
                                 depth_m=_noisy(true * rays[..., 2], rel, seed=10 + i) if rel else true * rays[..., 2],
                                 index=i, depth_noise_rel=rel))
    return RegionInput(0, Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0), images)


@pytest.mark.parametrize("kernel", [pytest.param("numba", marks=needs_numba), "numpy"])
def test_a_noisy_wall_is_fused_thin_and_exact_depth_gives_the_same_map_as_before(kernel):
    cfg = {"kernel": kernel, "remove_outliers": False}
    on = RECONSTRUCTORS.create("rgbd", cfg)
    off = RECONSTRUCTORS.create("rgbd", {**cfg, "denoise_window_px": 1})
    noisy = _wall_region(REL)
    thick = off.reconstruct(noisy).cloud
    thin = on.reconstruct(noisy).cloud
    # The wall is the plane x = 1.6 in the region's frame (start pose at the origin, heading 0).
    rms = [float(np.sqrt(np.mean((c.xyz[:, 0] - 1.6) ** 2))) for c in (thick, thin)]
    assert rms[1] < 0.5 * rms[0]
    assert len(thin) < 0.7 * len(thick)  # fewer voxels: the slab is gone
    exact = _wall_region(0.0)
    a, b = on.reconstruct(exact).cloud, off.reconstruct(exact).cloud
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb)


def test_a_denoised_frame_is_fused_as_far_as_its_denoised_sigma_allows():
    # sigma = rel * z^2 / window_px after denoising reaches max_depth_noise_m (4 cm) at sqrt(0.04 * 5 / 0.01)
    # = 4.47 m for rel 0.01; raw (window 1) at 2 m; exact depth to max_depth_m.
    im = _wall_region(REL, 1).images[0]
    assert RECONSTRUCTORS.create("rgbd").depth_limit_m(im) == pytest.approx(np.sqrt(20.0))
    assert RECONSTRUCTORS.create("rgbd", {"denoise_window_px": 1}).depth_limit_m(im) == pytest.approx(2.0)
    im.depth_noise_rel = 0.0
    assert RECONSTRUCTORS.create("rgbd").depth_limit_m(im) == 8.0
