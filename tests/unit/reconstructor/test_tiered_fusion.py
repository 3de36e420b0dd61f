"""Tiered fusion of frames that declare their depth noise (issue 33): where a near look saw a surface,
far looks add nothing to it (neither their scattered positions nor their colour); what only far looks
saw is kept; exact depth is fused in one tier as before."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.reconstructor.core import RECONSTRUCTORS, RegionInput, kernels
from services.reconstructor.core.frames import PosedImage
from shared.geometry import PinholeCamera, camera_pose
from shared.schemas import Pose

REL = 0.01  # bench.anticipation's noisy robot: sigma = 0.01 * z^2
WALL_X = 1.5
NEAR_RGB, FAR_RGB = (120, 120, 120), (200, 60, 60)


def _frames(rel: float, back: bool = False, near_drift_m: float = 0.0, far_m: float = 4.0,
            size_px: tuple[int, int] = (64, 48)) -> RegionInput:
    """The wall x = 1.5 m: four frames from 1.5 m away (grey) and four from 4 m (red), each with its own
    noise draw. The far frames also see the wall beyond the near frames' view (|y| > 1.5 m). With
    ``back``, the far frames look from the other side at the wall's far face, 10 cm behind (x = 1.6).
    ``near_drift_m``: the near frames believe they stand that much farther back (-x) than they do (the
    tour drifted after the far looks), so they place the wall that much nearer to them; ``far_m`` and
    ``size_px`` (width, height) place the far frames and size every image."""
    w, h = size_px
    cam = PinholeCamera(w, h, 90.0)
    images = []
    for i in range(8):
        near = i < 4
        x, face, heading = (0.0, WALL_X, 0.0) if near else (WALL_X - far_m, WALL_X, 0.0)
        if back and not near:
            x, face, heading = WALL_X + 0.1 + far_m, WALL_X + 0.1, np.pi
        rng = np.random.default_rng(40 + i)
        wfc = camera_pose(np.array([x - (near_drift_m if near else 0.0), 0.03 * (i % 4), 0.0]), heading, 0.0, 1.25)
        true = np.full((h, w), abs(face - x), np.float32)  # z-depth of the wall's face
        d = (true + rel * true**2 * rng.standard_normal(true.shape)).astype(np.float32) if rel else true
        rgb = np.empty((h, w, 3), np.uint8)
        rgb[:] = NEAR_RGB if near else FAR_RGB
        images.append(PosedImage(rgb=rgb, world_from_camera=wfc, camera=cam, depth_m=d, index=i,
                                 depth_noise_rel=rel))
    return RegionInput(0, Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0), images)


@pytest.mark.parametrize("kernel", [pytest.param("numba", marks=pytest.mark.skipif(
    not kernels.AVAILABLE, reason="numba not installed")), "numpy"])
def test_far_looks_add_only_what_no_near_look_saw(kernel):
    cfg = {"fusion": "voxels", "kernel": kernel, "remove_outliers": False}
    tiered = RECONSTRUCTORS.create("rgbd", cfg).reconstruct(_frames(REL)).cloud
    one = RECONSTRUCTORS.create("rgbd", {**cfg, "near_depth_noise_m": 0.0}).reconstruct(_frames(REL)).cloud
    for c in (tiered, one):
        assert (np.abs(c.xyz[:, 1]) > 2.0).sum() > 100  # what only the far looks saw is mapped either way
    core = [(np.abs(c.xyz[:, 1]) < 1.0) & (np.abs(c.xyz[:, 2] - 1.25) < 0.8) for c in (tiered, one)]
    # Where the near frames looked: their colour only, one layer near the wall; fused in one tier the
    # far frames' red and their 3 cm scatter were in it.
    # (a far draw 2.5 sigma out, 8 cm, can lie beyond near_cover_m: a few in a thousand)
    assert (tiered.rgb[core[0]] != NEAR_RGB).any(axis=1).mean() < 0.01
    assert (one.rgb[core[1]] != NEAR_RGB).any(axis=1).mean() > 0.1
    rms = [float(np.sqrt(np.mean((c.xyz[m, 0] - WALL_X) ** 2))) for c, m in zip((tiered, one), core)]
    assert rms[0] < 0.5 * rms[1]


def test_a_far_look_at_the_other_face_of_a_wall_is_kept():
    cfg = {"fusion": "voxels", "remove_outliers": False}
    region = _frames(REL, back=True)
    red = []
    for c in (RECONSTRUCTORS.create("rgbd", cfg).reconstruct(region).cloud,
              RECONSTRUCTORS.create("rgbd", {**cfg, "near_depth_noise_m": 0.0}).reconstruct(region).cloud):
        core = (np.abs(c.xyz[:, 1]) < 1.0) & (np.abs(c.xyz[:, 2] - 1.25) < 0.8)
        red.append(core & (c.rgb == FAR_RGB).all(axis=1))
        assert np.median(c.xyz[red[-1], 0]) == pytest.approx(WALL_X + 0.1, abs=0.02)
    # The far face, 10 cm behind the near one and within near_cover_m of it, was seen from the other
    # side: all of it is kept (fused in one tier, a few of its voxels also took near points' grey).
    assert red[1].sum() > 300 and red[0].sum() >= red[1].sum()


def test_a_far_patch_the_near_looks_placed_apart_is_kept():
    # The near looks drifted 4.5 cm: their wall, one tight layer, lies 4.5 cm in front of the true one.
    # The far looks saw the true wall; covered by the near layer (within near_cover_m) nothing of it would
    # be mapped within 3 cm. Kept as a patch apart, it is; its stray draws stay covered.
    region = _frames(REL, near_drift_m=0.045, far_m=3.2, size_px=(160, 120))  # far pixels 4 cm apart
    yy, zz = np.meshgrid(np.linspace(-0.9, 0.9, 37), np.linspace(0.6, 1.9, 27))
    wall = np.stack([np.full(yy.size, WALL_X), yy.ravel(), zz.ravel()], axis=1)
    mapped, red = [], []
    for offset_m in (0.03, 0.0):
        cfg = {"fusion": "voxels", "remove_outliers": False, "far_offset_m": offset_m}
        c = RECONSTRUCTORS.create("rgbd", cfg).reconstruct(region).cloud
        dist, _ = cKDTree(c.xyz).query(wall)
        mapped.append(float((dist <= 0.03).mean()))
        core = (np.abs(c.xyz[:, 1]) < 1.0) & (np.abs(c.xyz[:, 2] - 1.25) < 0.8)
        red.append(core & (c.rgb == FAR_RGB).all(axis=1))
        assert np.median(c.xyz[core & ~red[-1], 0]) == pytest.approx(WALL_X - 0.045, abs=0.01)
    assert mapped[0] > 0.9 and mapped[1] < 0.1, mapped
    kept = red[0].sum()
    assert kept > 300 and red[1].sum() < 0.05 * kept


def test_stray_far_draws_beyond_the_offset_stay_covered():
    # Isolated far points 5 cm off a near surface: a draw of the far looks' noise, not a placement.
    from services.reconstructor.core.regional import _fill_from_far
    from shared.cloud import PointCloud

    g = np.arange(0.0, 0.6, 0.03)
    yy, zz = np.meshgrid(g, g)
    near_xyz = np.stack([np.zeros(yy.size), yy.ravel(), zz.ravel()], axis=1)
    stray = np.array([[0.05, 0.36, 0.06], [0.05, 0.45, 0.3], [0.05, 0.54, 0.54], [0.05, 0.3, 0.45]])  # apart
    patch = near_xyz[(yy.ravel() < 0.2) & (zz.ravel() < 0.2)] + [0.05, 0.0, 0.0]  # a 7 x 7 patch, 3 cm apart
    view = lambda n: np.tile(np.array([[-127, 0, 0]], np.int8), (n, 1))
    rgb = lambda n: np.zeros((n, 3), np.uint8)
    near = PointCloud(near_xyz, rgb(len(near_xyz)), None, {}, view(len(near_xyz)))
    far = PointCloud(np.concatenate([stray, patch]), rgb(len(stray) + len(patch)), None, {},
                     view(len(stray) + len(patch)))
    kept = _fill_from_far(near, far, 0.1, offset_m=0.03, patch_m=0.06, patch_points=8).xyz[len(near):]
    d_stray = np.linalg.norm(kept[:, None] - stray[None], axis=2).min(axis=0)
    d_patch = np.linalg.norm(kept[:, None] - patch[None], axis=2).min(axis=0)
    assert (d_stray > 0.01).all()
    # the patch's 5 x 5 interior has 13 points within 6 cm of each of its own (its rim fewer)
    interior = (np.abs(patch[:, 1] - 0.09) < 0.07) & (np.abs(patch[:, 2] - 0.09) < 0.07)
    assert (d_patch[interior] < 1e-6).all() and interior.sum() == 25
    assert len(_fill_from_far(near, far, 0.1)) == len(near)  # no offset: everything within 10 cm is covered


def test_exact_depth_is_fused_in_one_tier_as_before():
    exact = _frames(0.0)
    a = RECONSTRUCTORS.create("rgbd").reconstruct(exact).cloud
    b = RECONSTRUCTORS.create("rgbd", {"near_depth_noise_m": 0.0}).reconstruct(exact).cloud
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb) and np.array_equal(a.view_dirs, b.view_dirs)
    assert (a.rgb == FAR_RGB).all(axis=1).any()  # (exact far looks are fused where near ones also looked)


def test_a_frame_splits_at_the_depth_where_its_denoised_sigma_reaches_the_near_tiers():
    rec = RECONSTRUCTORS.create("rgbd")
    im = _frames(REL).images[0]
    # sigma = rel / window_px * z^2 = 0.002 z^2 reaches near_depth_noise_m (1.5 cm) at sqrt(7.5) m
    assert rec.near_limit_m(im) == pytest.approx(np.sqrt(7.5))
    im.depth_noise_rel = 0.0
    assert rec.near_limit_m(im) == rec.depth_limit_m(im) == 8.0
