"""Voxel level of detail: a view draws about one point per pixel of a far surface however dense the
map, the points it draws stand for the mean of what they replace, and the image stays the image
of every point."""

from __future__ import annotations

import numpy as np
import pytest

import libs.pointrender.lod as lod_module
from shared.cloud import PointCloud, quantise_view_dirs, view_dirs_unit
from shared.geometry import PinholeCamera, camera_pose
from libs.pointrender import RENDERERS, IndexedCloud
from libs.pointrender.cloud import Frustum
from libs.pointrender.lod import build_voxel_lod, first_cell_m
from libs.pointrender.splat import point_normals_of, point_sides_of, point_spacing_of, share_point_geometry
from shared.schemas import ViewPose

CAM = PinholeCamera(128, 128, 90.0)


def _wall(x_m: float, half_m: float, step_m: float, checker_m: float | None = None, seed: int = 0,
          z_m: tuple[float, float] = (0.0, 2.5)) -> PointCloud:
    """A dense vertical wall at ``x = x_m`` (y in +-half_m, z in ``z_m``), grey or a red/blue checker."""
    ys, zs = np.arange(-half_m, half_m, step_m), np.arange(*z_m, step_m)
    yy, zz = np.meshgrid(ys, zs)
    n = yy.size
    xyz = np.column_stack([np.full(n, x_m), yy.ravel(), zz.ravel()])
    xyz += np.random.default_rng(seed).normal(0, step_m / 4, xyz.shape)
    rgb = np.full((n, 3), 128, np.uint8)
    if checker_m is not None:
        odd = ((np.floor(yy.ravel() / checker_m) + np.floor(zz.ravel() / checker_m)) % 2).astype(bool)
        rgb = np.where(odd[:, None], [[250, 0, 0]], [[0, 0, 250]]).astype(np.uint8)
    return PointCloud(xyz, rgb, np.zeros(n, np.int32), {0: "wall"})


def _view():
    return [ViewPose(position_m=(0.0, 0.0, 0.0))]


def test_drawn_points_follow_the_pixels_not_the_distance_or_density():
    # The same 2 cm wall 2 m and 8 m away: without LOD a view draws every point in the frustum
    # (more at 8 m: the frustum takes in more of the wall); with it, about the pixels covered. A pixel
    # is 12.5 cm at 8 m: the far wall has ~39 points a pixel, far more than the LOD draws (the checks
    # hold with a 3.5x margin; a 1 cm wall draws as many level points and only costs 4x to build).
    near, far = IndexedCloud(_wall(2.0, 2.0, 0.02)), IndexedCloud(_wall(8.0, 8.0, 0.02, seed=1))
    lod = RENDERERS.create("numpy")
    off = RENDERERS.create("numpy", {"lod_points_per_px": None})
    n_near = lod.render(near, _view(), CAM).visible_points[0]
    n_far = lod.render(far, _view(), CAM).visible_points[0]
    all_far = off.render(far, _view(), CAM).visible_points[0]
    assert n_far <= 4 * CAM.width_px * CAM.height_px, n_far
    assert n_far < all_far / 20, (n_far, all_far)
    assert n_far < n_near, (n_far, n_near)
    # and the wall is still a whole wall, at its depth
    out = lod.render(far, _view(), CAM)
    seen = ~out.hole_mask[0]
    assert seen[58:70].mean() > 0.99  # the rows that see the wall (2.5 m high, camera at 1.25 m)
    assert np.allclose(out.depth_m[0][seen], 8.0, atol=0.1)


def test_level_points_are_the_means_of_their_voxels():
    index = IndexedCloud(_wall(3.0, 1.0, 0.01, checker_m=0.02))
    lod = build_voxel_lod(index, point_spacing_of(index, 4), cell_m=0.04, levels=3)
    assert lod.cloud.xyz[: len(index)].tobytes() == index.cloud.xyz.tobytes()  # level 0 is the cloud
    assert len(lod.cloud) > len(index)
    for level in (1, 2, 3):
        n = int(lod.counts[level].sum())
        assert n < len(index) / 4 ** (level - 0.5), (level, n)
        start = int(lod.starts[level].min())
        rgb = lod.cloud.rgb[start : start + n].astype(float)
        # 2 cm checker in >= 4 cm cells: every level point mixes red and blue
        assert np.abs(rgb[:, 0] - rgb[:, 2]).mean() < 120, level
        assert (lod.spacing[start : start + n] >= lod.cell_m[level] - 1e-6).all()
    # blocks keep their points within their own bounds at every level
    for level in (1, 2, 3):
        for b in range(index.block_count):
            s, c = lod.starts[level, b], lod.counts[level, b]
            pts = lod.cloud.xyz[s : s + c]
            assert (pts >= index.block_min[b] - 1e-4).all() and (pts <= index.block_max[b] + 1e-4).all()


@pytest.fixture(scope="module")
def wall_and_floor() -> tuple[PointCloud, int, IndexedCloud]:
    """(cloud, points of the wall, index) of a wall at x = 1 and a floor meeting it, for both tests of
    the levels' normals, with the points' k-d tree, spacing and normals computed once on the index
    (another index of the same points takes them: share_point_geometry)."""
    wall = _wall(1.0, 0.5, 0.01)
    floor = PointCloud(wall.xyz[:, [2, 1, 0]] * [1.0, 1.0, 0.0] + [1.2, 0.0, 0.0], wall.rgb, wall.labels, wall.label_names)
    both = PointCloud.concatenate([wall, floor])
    index = IndexedCloud(both)
    point_normals_of(index, 10)
    point_spacing_of(index, 4)
    return both, len(wall), index


def test_level_normals_are_the_principal_axis_of_their_members_normals(wall_and_floor):
    # A wall (normal +-x) and a floor (normal +-z) meeting in one block: the PCA normals of the
    # points, and of every level's voxels away from the edge, are the surface's, whatever the sign.
    _, _, index = wall_and_floor
    normals = point_normals_of(index, 10)
    lod = build_voxel_lod(index, point_spacing_of(index, 4), cell_m=0.04, levels=3, normals=normals)
    assert np.allclose(np.linalg.norm(lod.normals, axis=1), 1.0, atol=1e-5)
    xyz = lod.cloud.xyz
    for axis, on_surface in ((0, np.abs(xyz[:, 0] - 1.0) < 0.02), (2, np.abs(xyz[:, 2]) < 0.02)):
        away = on_surface & (xyz[:, 2] > 0.2) if axis == 0 else on_surface & (xyz[:, 0] > 1.3)
        assert away.sum() > 100
        assert np.quantile(np.abs(lod.normals[away, axis]), 0.01) > 0.95, axis
    assert (np.abs(lod.normals[len(index):, 0]) > 0.95).any() and (np.abs(lod.normals[len(index):, 2]) > 0.95).any()


def test_a_far_checker_renders_its_mean_colour_and_matches_every_point():
    # 2 cm checker 6 m away: a pixel is 4.7 cm there. Drawn from its voxel levels, the wall shows
    # the checker's mean (purple), as drawing every point does, within a few levels. The checks read
    # rows 58-69 (z ~0.8-1.8 m at 6 m): the wall spans z 0.5-2 m, not 0-2.5 (180k points, not 300k).
    index = IndexedCloud(_wall(6.0, 6.0, 0.01, checker_m=0.02, z_m=(0.5, 2.0)))
    a = RENDERERS.create("numpy").render(index, _view(), CAM)
    b = RENDERERS.create("numpy", {"lod_points_per_px": None}).render(index, _view(), CAM)
    both = ~a.hole_mask[0] & ~b.hole_mask[0]
    assert both[58:70].mean() > 0.99
    ra, rb = a.rgb[0][both].astype(float), b.rgb[0][both].astype(float)
    assert abs(ra[:, 0].mean() - ra[:, 2].mean()) < 25  # purple, not red or blue pixels
    assert np.abs(ra.mean(axis=0) - rb.mean(axis=0)).max() < 10
    assert a.visible_points[0] < b.visible_points[0] / 5


def test_each_mode_draws_its_own_cell_size_unless_one_is_set():
    # The visibility mode's footprints follow each level's spacing, so it draws cells up to 2.5 px
    # (LOD_CELL_PX); the paper's fixed 3x3 splat would show 2 px gaps as holes, so it keeps 1 px.
    from libs.pointrender.splat import LOD_CELL_PX

    # A 2 cm wall 4 m away (a pixel is 6.25 cm there): finer than the cells either mode draws, so both
    # draw voxel levels, and the modes differ only by their cell size in pixels.
    wall = IndexedCloud(_wall(4.0, 4.0, 0.02))
    drawn = {mode: RENDERERS.create("numpy", {"mode": mode}).render(wall, _view(), CAM).visible_points[0]
             for mode in ("visibility", "paper")}
    assert LOD_CELL_PX == {"visibility": 2.5, "paper": 1.0}
    assert drawn["visibility"] < 0.5 * drawn["paper"], drawn
    same = RENDERERS.create("numpy", {"mode": "visibility", "lod_cell_px": 1.0}).render(wall, _view(), CAM)
    assert same.visible_points[0] == drawn["paper"]
    # ... and the paper mode still closes its wall at 1 px cells.
    paper = RENDERERS.create("numpy", {"mode": "paper"}).render(wall, _view(), CAM)
    assert (~paper.hole_mask[0][56:72]).mean() > 0.99


def test_renderers_of_one_cell_size_build_the_levels_once_and_each_gets_a_fresh_builds_lod(monkeypatch):
    # Paper mode (no normals), the slope tolerance (normals) and the unseen side (sided normals) on
    # one map with one cell size: the levels' points are built once and shared, each setting sums its
    # own normals over them, and every LOD equals a build from scratch. A coarser lod_cell_m that this
    # cloud's spacing halves to the same first cell shares them too; a first cell of its own builds its own.
    import libs.pointrender.renderer as renderer_module

    built = []
    build = renderer_module.build_voxel_geometry
    monkeypatch.setattr(renderer_module, "build_voxel_geometry", lambda *a: built.append(a[2:]) or build(*a))
    wall = _wall(2.0, 1.0, 0.02)
    toward_x = quantise_view_dirs(np.tile([-1.0, 0.0, 0.0], (len(wall), 1)))
    index = IndexedCloud(PointCloud(wall.xyz, wall.rgb, wall.labels, wall.label_names, toward_x))
    settings = ({"mode": "paper"}, {"unseen_side": False}, {}, {"lod_cell_m": 0.16},
                {"lod_cell_m": 0.16, "lod_cell_spacings": 3.0})
    renderers = [RENDERERS.create("numpy", s) for s in settings]
    lods = [r._voxel_lod(index) for r in renderers]
    assert [lod.normals is None for lod in lods] == [True, False, False, False, False]
    assert [lod.sided is None for lod in lods] == [True, True, False, False, False]
    cell_m = lods[0].cell_m[1]
    assert [lod.cell_m[1] for lod in lods[:4]] == [cell_m] * 4 and lods[4].cell_m[1] > cell_m
    assert built == [(cell_m, 5), (lods[4].cell_m[1], 5)]
    assert all(lod.cloud is lods[0].cloud and lod.spacing is lods[0].spacing for lod in lods[:4])  # shared
    spacing = point_spacing_of(index, 4)
    for r, lod in zip(renderers, lods):
        fresh = build_voxel_lod(index, spacing, lod.cell_m[1], 5, *(r._normals_of(index) or (None, None)))
        for name in ("starts", "counts", "cell_m", "spacing", "normals", "sided"):
            a, b = getattr(lod, name), getattr(fresh, name)
            assert (a is None and b is None) or np.array_equal(a, b), name
        for name in ("xyz", "rgb", "labels"):
            assert np.array_equal(getattr(lod.cloud, name), getattr(fresh.cloud, name)), name


def test_compiled_level_selection_picks_the_runs_the_array_code_picks(room_index, monkeypatch):
    if lod_module.select_runs is None:
        pytest.skip("numba is not installed: only the array code runs")
    # The flat's LOD as the renderer builds it (cached on the session's index, so the 1e6-point levels
    # are built once for every test that renders the flat).
    lod = RENDERERS.create("numpy", {"mode": "paper"})._voxel_lod(room_index)
    assert lod.levels == 5
    frustum = Frustum.for_camera(CAM, 0.05, 20.0)
    rng = np.random.default_rng(5)
    lo, hi = room_index.cloud.xyz.min(axis=0), room_index.cloud.xyz.max(axis=0)
    level0 = set(lod.starts[0].tolist())
    fine = coarse = 0
    for k in range(60):
        pose = camera_pose(rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi), 0.0, 1.25)
        mask = None if k % 3 == 0 else room_index.visible_blocks(pose, frustum)
        for cell_px in (1.0, 2.0, 3.0):
            compiled = lod.select(room_index, mask, pose, CAM.fx, cell_px)
            with monkeypatch.context() as m:
                m.setattr(lod_module, "select_runs", None)
                array = lod.select(room_index, mask, pose, CAM.fx, cell_px)
            assert np.array_equal(compiled[0], array[0]) and np.array_equal(compiled[1], array[1])
            at_level0 = np.isin(compiled[0], list(level0))
            fine, coarse = fine + int(at_level0.sum()), coarse + int((~at_level0).sum())
    assert fine > 0 and coarse > 0, (fine, coarse)  # both full-resolution and voxel levels were chosen


def test_a_denser_cloud_gets_a_finer_first_level_and_draws_fewer_points_at_mid_range():
    # A wall 1 m away sampled every 1 cm: at this focal length (64 px) 4 cm first-level cells reach
    # 2 px only beyond 1.28 m, so every point would be drawn; the cloud's own first level (2 cm, 2 px
    # from 0.64 m) merges them. A 3 cm cloud (what the reconstructor makes) keeps 4 cm.
    assert first_cell_m(np.full(10, 0.011), 0.04, 1.3) == 0.02
    assert first_cell_m(np.full(10, 0.030), 0.04, 1.3) == 0.04
    assert first_cell_m(np.full(10, 0.003), 0.04, 1.3) == 0.005
    dense = IndexedCloud(_wall(1.0, 1.5, 0.01))
    auto, fixed = RENDERERS.create("numpy"), RENDERERS.create("numpy", {"lod_cell_spacings": 8.0})
    assert auto._voxel_lod(dense).cell_m[1] == 0.02 and fixed._voxel_lod(dense).cell_m[1] == 0.04
    a, f = auto.render(dense, _view(), CAM), fixed.render(dense, _view(), CAM)
    assert a.visible_points[0] < 0.6 * f.visible_points[0], (a.visible_points, f.visible_points)
    seen = ~a.hole_mask[0]
    assert np.array_equal(seen, ~f.hole_mask[0]) and np.allclose(a.depth_m[0][seen], f.depth_m[0][seen], atol=0.03)


def test_level_normals_turn_towards_the_side_their_members_were_seen_from(wall_and_floor):
    # A wall at x = 1 seen from x < 1, and a floor seen from above: every level keeps the side
    # (normal towards the cameras, known), and a level whose members disagree knows none.
    both, n_wall, plain = wall_and_floor
    view = np.concatenate([np.tile([-1.0, 0.0, 0.0], (n_wall, 1)), np.tile([0.0, 0.0, 1.0], (len(both) - n_wall, 1))])
    index = IndexedCloud(PointCloud(both.xyz, both.rgb, both.labels, both.label_names, quantise_view_dirs(view)))
    assert share_point_geometry(plain, index) == 3  # the k-d tree, the spacing and the normals
    normals, sided = point_sides_of(index, 10, None, 0.2)
    lod = build_voxel_lod(index, point_spacing_of(index, 4), cell_m=0.04, levels=3, normals=normals, sided=sided)
    xyz = lod.cloud.xyz
    on_wall = (np.abs(xyz[:, 0] - 1.0) < 0.02) & (xyz[:, 2] > 0.2)
    on_floor = (np.abs(xyz[:, 2]) < 0.02) & (xyz[:, 0] > 1.3)
    for sel, axis, sign in ((on_wall, 0, -1.0), (on_floor, 2, 1.0)):
        assert sel[len(index):].sum() > 50
        assert (lod.sided[sel] == 1).mean() > 0.99
        assert np.quantile(sign * lod.normals[sel, axis], 0.01) > 0.95
    # Every other point seen from the other side: its levels' sides cancel (a voxel of a few
    # members, cut by a block's edge, may still hold a 3:1 majority).
    flip = np.where(np.arange(len(index)) % 2 == 0, 1.0, -1.0)[:, None]
    index2 = IndexedCloud(PointCloud(index.cloud.xyz, index.cloud.rgb, index.cloud.labels, index.cloud.label_names,
                                     quantise_view_dirs(view_dirs_unit(index.cloud.view_dirs) * flip)))
    normals2, sided2 = point_sides_of(index2, 10, None, 0.2)
    lod2 = build_voxel_lod(index2, point_spacing_of(index2, 4), 0.04, 3, normals2, sided2)
    levels = np.arange(len(lod2.cloud)) >= len(index2)
    assert lod2.sided[levels].mean() < 0.1 and (lod.sided[levels] == 1).mean() > 0.9
