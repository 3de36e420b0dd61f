"""Thinning across the surfaces of a region whose frames declare their depth noise (issue 33): the
sparse outer layers that every look's scatter leaves in front of and behind a wall are dropped, the
wall's own layer and a wall's far face seen from the other side are kept, exact depth is untouched."""

from __future__ import annotations

import numpy as np
import pytest

from services.reconstructor.core import RECONSTRUCTORS, RegionInput, kernels
from shared.geometry import PinholeCamera
from tests.unit.reconstructor.walls import wall_frames

REL = 0.01  # bench.anticipation's noisy robot: sigma = 0.01 * z^2
WALL_X = 1.515  # the middle of a 3 cm voxel: exact depth fuses it in one layer
AWAY_M = 2.5  # denoised sigma 0.002 * 2.5^2 = 1.25 cm: still the near tier, a slab of ~3 layers


def _frames(rel: float, back: int = 0, thick_m: float = 0.1) -> RegionInput:
    """Eight frames of the wall x = WALL_X from 2.5 m (walls.wall_frames), 64 x 48 px."""
    return wall_frames(rel, WALL_X, AWAY_M, PinholeCamera(64, 48, 90.0), back, thick_m)


THIN = {"surface_share": 0.4}


def _core(c, face: float, side: int = 0):
    """Points of the central patch within 10 cm of ``face``; how many lie outside the face's own voxel
    (``side`` -1: only those on the lower-x side, +1: the higher-x side, 0: either)."""
    m = (np.abs(c.xyz[:, 1]) < 1.0) & (np.abs(c.xyz[:, 2] - 1.25) < 0.7) & (np.abs(c.xyz[:, 0] - face) < 0.1)
    off = c.xyz[:, 0] - face
    return m.sum(), (m & ((off * side > 0.015) if side else (np.abs(off) > 0.015))).sum()


@pytest.mark.parametrize("kernel", [pytest.param("numba", marks=pytest.mark.skipif(
    not kernels.AVAILABLE, reason="numba not installed")), "numpy"])
def test_the_sparse_outer_layers_of_a_noisy_wall_are_dropped(kernel):
    # The slab as the voxels fuse it (noisy depth's default is the TSDF), strays and all.
    cfg = {"fusion": "voxels", "kernel": kernel, "remove_outliers": False, "stray_points": 0}
    thin = RECONSTRUCTORS.create("rgbd", {**cfg, **THIN}).reconstruct(_frames(REL)).cloud
    slab = RECONSTRUCTORS.create("rgbd", cfg).reconstruct(_frames(REL)).cloud
    (n_thin, off_thin), (n_slab, off_slab) = _core(thin, WALL_X), _core(slab, WALL_X)
    assert off_slab > 500  # the scatter's outer layers (sigma 1.25 cm: a quarter of the draws each side)
    assert off_thin < 0.85 * off_slab
    # The wall itself stays covered: its own layer has a point in (almost) every voxel it had.
    assert n_thin - off_thin >= 0.97 * (n_slab - off_slab)


def test_behind_drops_only_the_layers_behind_the_wall():
    cfg = {"fusion": "voxels", "remove_outliers": False, "stray_points": 0}
    slab = RECONSTRUCTORS.create("rgbd", cfg).reconstruct(_frames(REL)).cloud
    behind = RECONSTRUCTORS.create("rgbd", {**cfg, **THIN, "surface_sides": "behind"}).reconstruct(_frames(REL)).cloud
    # The frames look along +x: behind the wall is the higher-x side.
    assert _core(slab, WALL_X, +1)[1] > 200 and _core(behind, WALL_X, +1)[1] < 0.85 * _core(slab, WALL_X, +1)[1]
    assert _core(slab, WALL_X, -1)[1] > 200 and _core(behind, WALL_X, -1)[1] == _core(slab, WALL_X, -1)[1]


def test_a_wall_seen_from_both_sides_keeps_both_faces():
    cfg = {"fusion": "voxels", "remove_outliers": False, "stray_points": 0}
    # A thin one (6 cm: a cabinet's side), its far face seen by one frame: within reach of the near
    # face's eight, whose voxels hold many more points.
    region = _frames(REL, back=1, thick_m=0.06)
    thin = RECONSTRUCTORS.create("rgbd", {**cfg, **THIN}).reconstruct(region).cloud
    slab = RECONSTRUCTORS.create("rgbd", cfg).reconstruct(region).cloud
    # The far face is no outer layer of the near face: the share is taken among voxels seen from the
    # same side only.
    far_thin, far_slab = _core(thin, WALL_X + 0.06), _core(slab, WALL_X + 0.06)
    assert far_slab[0] - far_slab[1] > 200
    assert far_thin[0] - far_thin[1] >= 0.97 * (far_slab[0] - far_slab[1])


def test_exact_depth_is_not_thinned():
    exact = _frames(0.0)
    a = RECONSTRUCTORS.create("rgbd", THIN).reconstruct(exact).cloud
    b = RECONSTRUCTORS.create("rgbd").reconstruct(exact).cloud
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb) and np.array_equal(a.view_dirs, b.view_dirs)
