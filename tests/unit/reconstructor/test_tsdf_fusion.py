"""TSDF fusion of a region whose frames declare their depth noise (RgbdConfig.fusion "tsdf", issue 33): a
noisy wall comes out as one sheet on the true plane where the voxel fusion leaves a slab; the points keep
their colour, label and view direction; a wall's far face seen from the other room stays; exact depth is
fused as before; the array code (kernel "numpy", or numba missing) gives the compiled loops' bits; the map
is one volume of every region's frames (tsdf_scope "map"), so a near region's looks outvote a far one's."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.reconstructor.core import (RECONSTRUCTORS, InputError, ReconstructionConfig, Reconstructor, RegionInput,
                                         kernels)
from services.reconstructor.core import regional
from services.reconstructor.core.frames import PosedImage, region_from_frames
from services.reconstructor.core.registration import se2, transform_cloud, transform_region
from shared.cloud import view_dirs_unit
from shared.geometry import PinholeCamera
from tests.unit.reconstructor.test_reconstructor_kernels import _region
from tests.unit.reconstructor.walls import wall_frames

needs_numba = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed: nothing to compare with")

REL = 0.01  # bench.anticipation's noisy robot: sigma = 0.01 * z^2
WALL_X = 1.507  # off the 3 cm grid's centres and faces: no fusion finds the plane by its grid alone
AWAY_M = 2.5  # raw sigma 6.25 cm, denoised 1.25 cm: the voxel fusion's near tier
LABEL = 7
TSDF = {"fusion": "tsdf"}


def _frames(rel: float, back: int = 0, thick_m: float = 0.1) -> RegionInput:
    """Eight frames of the wall x = WALL_X from AWAY_M (walls.wall_frames), labelled; a pixel 2.6 cm wide at
    AWAY_M: narrower than a voxel."""
    return wall_frames(rel, WALL_X, AWAY_M, PinholeCamera(192, 144, 90.0), back, thick_m, label=LABEL)


def _patch(c, face: float):
    """The points of the wall's central patch within 10 cm of ``face``: (mask, their distance to it)."""
    m = (np.abs(c.xyz[:, 1]) < 1.0) & (np.abs(c.xyz[:, 2] - 1.25) < 0.7) & (np.abs(c.xyz[:, 0] - face) < 0.1)
    return m, np.abs(c.xyz[m, 0] - face)


def test_a_noisy_wall_is_one_sheet_on_its_plane():
    voxels = RECONSTRUCTORS.create("rgbd", {"fusion": "voxels"}).reconstruct(_frames(REL)).cloud
    tsdf = RECONSTRUCTORS.create("rgbd", TSDF).reconstruct(_frames(REL)).cloud
    (mv, off_v), (mt, off_t) = _patch(voxels, WALL_X), _patch(tsdf, WALL_X)
    # The voxel fusion's centroids scatter over the slab: 27 % of them more than 1.5 cm off the plane, the
    # farthest 4.4 cm. The signed distance averages every look along the wall's normal: 0.3 %, at most 1.9 cm.
    assert (off_v > 0.015).mean() > 0.15 and off_v.max() > 0.035
    assert (off_t > 0.015).mean() < 0.02 and off_t.max() < 0.025
    # The patch (2 m x 1.4 m) stays covered: a point in most of its 3 cm squares.
    cells = np.unique(np.floor(tsdf.xyz[mt][:, 1:] / 0.03).astype(np.int64), axis=0)
    assert len(cells) >= 0.9 * (2.0 / 0.03) * (1.4 / 0.03)


def test_the_points_keep_colour_label_and_where_they_were_seen_from():
    c = RECONSTRUCTORS.create("rgbd", TSDF).reconstruct(_frames(REL)).cloud
    m, _ = _patch(c, WALL_X)
    assert (c.rgb[m] == 120).all() and (c.labels[m] == LABEL).all()
    # Seen from the lower-x side only: the mean direction towards the cameras points along -x, unit long.
    v = view_dirs_unit(c.view_dirs[m])
    assert (v[:, 0] < -0.8).all() and (np.linalg.norm(v, axis=1) > 0.95).all()


def test_a_wall_seen_from_both_sides_keeps_both_faces():
    # Eight looks at the near face, two at the far face 10 cm behind it (another room): the near face's
    # band behind the surface stops short of the far face, which keeps its own colour and side.
    c = RECONSTRUCTORS.create("rgbd", TSDF).reconstruct(_frames(REL, back=2)).cloud
    mf, off_f = _patch(c, WALL_X + 0.1)
    far = mf & (c.xyz[:, 0] > WALL_X + 0.05)
    assert far.sum() > 0.8 * _patch(c, WALL_X)[0].sum() / 2
    # (A near-face draw 3.5 sigma behind its surface can still reach a far-face voxel: 1 point in 4370 here,
    # as in the voxel fusion, 1 in 3896.)
    assert (c.rgb[far] == 200).all(axis=1).mean() > 0.999
    assert (view_dirs_unit(c.view_dirs[far])[:, 0] > 0.8).mean() > 0.999


def test_exact_depth_is_fused_in_voxels_as_before():
    exact = _frames(0.0)
    a = RECONSTRUCTORS.create("rgbd", TSDF).reconstruct(exact).cloud
    b = RECONSTRUCTORS.create("rgbd").reconstruct(exact).cloud
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb) and np.array_equal(a.view_dirs, b.view_dirs)
    assert np.array_equal(a.labels, b.labels)


def _volumes(region: RegionInput, cfg: dict):
    """``region``'s TSDF volume by the compiled loops and by the array code, with its cloud."""
    out = []
    for kernel in ("numba", "numpy"):
        rgbd = RECONSTRUCTORS.create("rgbd", {**TSDF, **cfg, "kernel": kernel})
        assert rgbd.kernel == kernel
        c = rgbd.config
        labelled = all(im.semantic is not None for im in region.images)
        vol = rgbd.tsdf_volume(region.images, region.local_from_world(), labelled)
        out.append((vol, vol.cloud(c.tsdf_min_updates, c.tsdf_crossing_max_vox, c.tsdf_fill_m)))
    return out


def _assert_same_bits(region: RegionInput, cfg: dict) -> int:
    """The two paths' volumes (every sum, in the same entry order) and clouds are equal; returns the points."""
    (va, a), (vb, b) = _volumes(region, cfg)
    assert va.n == vb.n > 0 and va.points == vb.points > 0
    assert np.array_equal(va.keys[: va.n], vb.keys[: vb.n]) and np.array_equal(va.rows[: va.n], vb.rows[: vb.n])
    assert len(a) == len(b) > 0
    for got, want in ((a.xyz, b.xyz), (a.rgb, b.rgb), (a.labels, b.labels), (a.view_dirs, b.view_dirs)):
        assert np.array_equal(got, want)
    return len(a)


@needs_numba
@pytest.mark.parametrize("cfg", [{}, {"pixel_stride": 3, "tsdf_max_sub_rays": 3, "tsdf_fill_m": 0.06}],
                         ids=["one-ray", "sub-rays"])
def test_the_array_path_gives_the_compiled_bits_on_the_wall(cfg):
    # Both faces, two colours and labels; stride 3 makes a pixel 7.8 cm wide at 2.5 m: three rays a side.
    assert _assert_same_bits(_frames(REL, back=2), cfg) > 3000


@needs_numba
def test_the_array_path_gives_the_compiled_bits_on_mixed_labels():
    # Random depth, holes, NaN and up to five labels in a 10 cm voxel: the label majority steps through
    # voxels that see several labels in one frame, where its order decides.
    region = _region(7, seed=1)
    for im in region.images:
        im.depth_noise_rel = REL
    (va, _), _ = _volumes(region, {"tsdf_voxel_m": 0.1})
    labels = va.rows[: va.n, 6]
    assert (labels > 0).sum() > 1000 and len(np.unique(labels)) == 5  # none and four labels: all compete
    assert _assert_same_bits(region, {"tsdf_voxel_m": 0.1}) > 100


@pytest.fixture(scope="module")
def look_around():
    """A noisy robot's look-around in a generated house (+-60 deg yaw, +-45 deg pitch): one hub's frames."""
    from services.robot_io.core import ROBOTS

    robot = ROBOTS.create("sim", {"scene": "generated:3:area=50", "camera": {"width_px": 48, "height_px": 48},
                                  "noise": {"depth_noise_rel": REL}})
    try:
        frames = robot.look_around()
    finally:
        robot.close()
    return region_from_frames(0, frames[0].pose, frames)


@needs_numba
def test_the_array_path_gives_the_compiled_bits_on_a_look_around(look_around):
    assert len(look_around.images) > 20 and all(im.depth_noise_rel == REL for im in look_around.images)
    assert _assert_same_bits(look_around, {}) > 2000


def test_without_numba_the_array_path_fuses(monkeypatch, look_around):
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    rgbd = RECONSTRUCTORS.create("rgbd", TSDF)
    assert rgbd.kernel == "numpy"
    c = rgbd.reconstruct(look_around).cloud
    assert len(c) > 2000 and (c.labels >= 0).mean() > 0.9


@pytest.mark.parametrize("kernel", [pytest.param("numba", marks=needs_numba), "numpy"])
def test_points_out_of_range_raise_in_both_paths(kernel):
    region = _region(2, far=True)
    for im in region.images:
        im.depth_noise_rel = REL
    with pytest.raises(InputError, match="span more than"):
        RECONSTRUCTORS.create("rgbd", {**TSDF, "kernel": kernel, "tsdf_voxel_m": 0.01}).reconstruct(region)


@pytest.mark.parametrize("kernel", [pytest.param("numba", marks=needs_numba), "numpy"])
def test_a_frame_of_one_strided_pixel_is_counted_and_adds_nothing(kernel):
    # One pixel has no neighbour to measure its width by: the loop walks no ray for it (zero sub-rays).
    cam = PinholeCamera(16, 16, 90.0)
    im = PosedImage(rgb=np.zeros((16, 16, 3), np.uint8), world_from_camera=np.eye(4), camera=cam,
                    depth_m=np.full((16, 16), 1.5, np.float32), semantic=np.zeros((16, 16), np.int32), index=0,
                    depth_noise_rel=REL)
    rgbd = RECONSTRUCTORS.create("rgbd", {**TSDF, "kernel": kernel, "pixel_stride": 16})
    vol = rgbd.tsdf_volume([im], np.eye(4), True)
    assert vol.points == 1 and vol.n == 0


def _build(regions: list[RegionInput], scope: str, stages: bool = True, **backend):
    """The map the pipeline builds of ``regions`` with the TSDF over ``scope`` (without the stands' and drives'
    registration when not ``stages``; ``backend``: more of RgbdConfig)."""
    off = {} if stages else {"registration": {"stands": {"enabled": False}, "moves": {"enabled": False}}}
    config = ReconstructionConfig(backend="rgbd", backend_config={**TSDF, "tsdf_scope": scope, **backend}, **off)
    with Reconstructor(config) as r:
        return r.build(regions)


def _two_rooms_build(scope: str):
    """The wall seen by one region from 1 m (eight looks) and by another from 4.2 m, two looks (the next
    room's, across it: denoised sigma 3.5 cm), built by the pipeline with the TSDF over ``scope``."""
    near = wall_frames(REL, WALL_X, 1.0, PinholeCamera(192, 144, 90.0))
    far = wall_frames(REL, WALL_X, 4.2, PinholeCamera(192, 144, 90.0))
    far = replace(far, region=1, images=[replace(im, index=100 + im.index) for im in far.images[:2]])
    return _build([near, far], scope, stages=False)


def test_one_volume_for_the_map_lets_the_near_looks_outvote_the_far_region():
    apart, together = _two_rooms_build("region"), _two_rooms_build("map")
    # Apart, the far region keeps its own sheet beside the near one's: its two looks' scatter reaches 3 cm
    # and more off the plane (what a view of the wall from the near room saw as speckle).
    _, off_apart = _patch(apart.cloud, WALL_X)
    _, off_together = _patch(together.cloud, WALL_X)
    assert (off_apart > 0.03).sum() > 50
    assert (off_together > 0.03).sum() <= 0.1 * (off_apart > 0.03).sum()
    assert np.quantile(off_together, 0.99) < 0.015
    # The regions still each have their own cloud and report; the map's build time says what it cost.
    assert len(together.regional_clouds) == 2 and "fuse_map" in together.timings_s
    assert together.details()["fused_as_one_volume"] == [0, 1]
    assert "fuse_map" not in apart.timings_s and apart.details()["fused_as_one_volume"] == []


def test_exact_depth_maps_are_their_regions_clouds_whatever_the_scope():
    a, b = _build([_frames(0.0)], "map"), _build([_frames(0.0)], "region")
    assert np.array_equal(a.cloud.xyz, b.cloud.xyz) and np.array_equal(a.cloud.rgb, b.cloud.rgb)
    assert "fuse_map" not in a.timings_s and a.fused_regions == []


def test_a_region_moved_by_its_correction_fuses_where_its_cloud_went():
    # The regions' stage moves each region's cloud by a planar transform; the map's volume takes the region's
    # images moved by the same one, so both put the wall in the same place.
    region = _frames(REL)
    t = se2(0.2, -0.1, np.radians(10.0))
    rgbd = RECONSTRUCTORS.create("rgbd", TSDF)
    moved, _ = rgbd.fuse_map([transform_region(region, t)])
    want, _ = rgbd.fuse_map([region])
    want = transform_cloud(want, t)
    assert abs(len(moved) - len(want)) <= 0.01 * len(want) and len(want) > 3000
    dist, _ = cKDTree(want.xyz).query(moved.xyz)
    assert np.quantile(dist, 0.99) < 1e-3  # the same wall: the grid turned with it


@pytest.mark.parametrize("store_mb", [256, 1])
def test_the_maps_volume_takes_the_depth_its_regions_denoised(monkeypatch, store_mb):
    # The map's volume takes every noisy frame again: each frame's depth is denoised once, for its region's
    # volume, and kept for the map's (within map_depth_store_mb; 1 MB holds nine of these 192 x 144 frames,
    # the others are denoised again). The map is the one built without keeping anything, bit for bit.
    near = wall_frames(REL, WALL_X, 1.0, PinholeCamera(192, 144, 90.0))
    far = wall_frames(REL, WALL_X, 4.2, PinholeCamera(192, 144, 90.0))
    regions = [near, replace(far, region=1, images=[replace(im, index=100 + im.index) for im in far.images])]
    frames = sum(len(r.images) for r in regions)
    calls = []
    real = regional.denoise_depth
    monkeypatch.setattr(regional, "denoise_depth", lambda *a, **k: calls.append(1) or real(*a, **k))
    fresh = _build(regions, "map", stages=False, map_depth_store_mb=0)
    assert len(calls) == 2 * frames
    calls.clear()
    kept = _build(regions, "map", stages=False, map_depth_store_mb=store_mb)
    assert len(calls) == (frames if store_mb == 256 else 2 * frames - 9)
    for got, want in ((kept.cloud.xyz, fresh.cloud.xyz), (kept.cloud.rgb, fresh.cloud.rgb),
                      (kept.cloud.view_dirs, fresh.cloud.view_dirs)):
        assert got.tobytes() == want.tobytes()


def test_nothing_is_kept_after_the_map_is_fused():
    rgbd = RECONSTRUCTORS.create("rgbd", TSDF)
    region = _frames(REL)
    rgbd.reconstruct(region)
    assert len(rgbd._kept) == len(region.images) and rgbd._kept_bytes > 0
    rgbd.fuse_map([region])
    assert rgbd._kept == {} and rgbd._kept_bytes == 0
    rgbd.reconstruct(region)
    rgbd.close()  # a build that stops before the map's volume lets go of them too
    assert rgbd._kept == {} and rgbd._kept_bytes == 0


def test_a_backend_that_fuses_no_map_volume_keeps_no_depth_for_one():
    # mono-sim fuses each region with its own RGB-D fusion and scales it on its own: no map volume ever
    # takes the frames again, so nothing may stay held for one (256 MB at most, until the backend goes).
    mono = RECONSTRUCTORS.create("mono-sim", {"fusion": TSDF})
    mono.reconstruct(_frames(REL))
    assert mono._fusion._kept == {} and mono._fusion._kept_bytes == 0
    assert mono.fuse_map([_frames(REL)]) is None
