"""The ``visibility`` mode: no room behind a near wall, no holes in it, no surface invented across a
depth edge or a doorway, labels that follow the visible surface, and numpy == torch."""

from __future__ import annotations

import numpy as np
import pytest

from services.renderer.tools import scenes
from shared.cloud import PointCloud, quantise_view_dirs
from shared.geometry import PinholeCamera
from libs.pointrender import RENDERERS, IndexedCloud, visibility, visibility_kernels
from libs.pointrender.ops_numpy import point_tree_of
from libs.pointrender.splat import point_normals_of, point_spacing_of, share_point_geometry
from shared.schemas import ViewPose

CAM = PinholeCamera(256, 256, 90.0)
LEAK_M = 0.25  # as in bench.anticipation


def _lattice(x_m: float, y_m: tuple[float, float], z_m: tuple[float, float], step_m: float, colour, label: int,
             jitter_m: float = 0.003, seed: int = 0) -> PointCloud:
    """A vertical wall at ``x = x_m`` sampled like an agent-built map: a voxel lattice of
    ``step_m`` with a little jitter (the rgbd map of generated:0 has 2.6 cm median spacing)."""
    ys = np.arange(y_m[0], y_m[1], step_m)
    zs = np.arange(z_m[0], z_m[1], step_m)
    yy, zz = np.meshgrid(ys, zs)
    n = yy.size
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([np.full(n, x_m), yy.ravel(), zz.ravel()]) + rng.normal(0, jitter_m, (n, 3))
    return PointCloud(xyz, np.tile(np.array(colour, np.uint8), (n, 1)), np.full(n, label, np.int32),
                      {0: "wall", 1: "next room"})


def _wall_and_room(near_x_m: float) -> IndexedCloud:
    near = _lattice(near_x_m, (-1.5, 1.5), (0.0, 2.6), 0.025, (200, 30, 30), 0)
    room = _lattice(near_x_m + 3.0, (-4.0, 4.0), (0.0, 2.6), 0.025, (30, 30, 200), 1, seed=1)
    return IndexedCloud(PointCloud.concatenate([near, room]))


@pytest.fixture(scope="module")
def wall_half_a_metre_away() -> IndexedCloud:
    """``_wall_and_room(0.5)`` for the three tests that render it: what a render derives from the
    points (their k-d tree, spacing, normals and voxel levels) is cached on the index, so it is
    computed once, not once per test."""
    return _wall_and_room(0.5)


def _render(mode: str, index: IndexedCloud, backend: str = "numpy", **cfg):
    extra = {"device": "cpu"} if backend == "torch" else {}
    r = RENDERERS.create(backend, {"mode": mode, **extra, **cfg})
    return r.render(index, [ViewPose(position_m=(0.0, 0.0, 0.0))], CAM)


def _leak_and_holes(out, near_x_m: float) -> tuple[float, float]:
    depth, hole = out.depth_m[0], out.hole_mask[0]
    # Every pixel of this view sees the near wall (it spans +-71 deg horizontally at 0.5 m and the
    # camera at 1.25 m sees 1.25 m down and 1.35 m up at most): true z-depth = near_x_m.
    seen = ~hole
    leak = float((depth[seen] > near_x_m + LEAK_M).mean())
    return leak, float(hole.mean())


def test_no_leak_at_a_wall_half_a_metre_away(wall_half_a_metre_away):
    index = wall_half_a_metre_away
    leak, holes = _leak_and_holes(_render("visibility", index), 0.5)
    assert leak <= 0.01, leak
    assert holes <= 0.02, holes
    # The paper's fixed 3x3 splat shows the next room through the gaps of the same wall: the
    # assertions above fail for it (measured: leak 0.57, holes 0.48).
    p_leak, p_holes = _leak_and_holes(_render("paper", index), 0.5)
    assert p_leak > 0.2 and not (p_leak <= 0.01 and p_holes <= 0.02), (p_leak, p_holes)


@pytest.mark.parametrize("distance_m", [0.4, 0.5, 0.7])
def test_no_leak_and_no_holes_along_the_image_border(distance_m):
    # A wall sampled at the maps' merge voxel (3 cm: ~6-10 px apart at these distances) with a
    # room behind it. Near the border, a pixel's quadrant towards the edge used to hold only the
    # few columns inside the image: where those held no point of the wall but one of the room,
    # the room passed the visibility test (measured at 0.4 / 0.5 / 0.7 m: 6.7 / 9.1 / 2.4 % of
    # the 8 px border strip; most of the leak below 1 m on the agent-built maps). The guard band
    # projects the wall past the edge as well; and the last row and column, alone with the ring
    # in every pyramid cell before the pyramid was centred, get filled like any other pixel.
    near = _lattice(distance_m, (-1.5, 1.5), (0.0, 2.6), 0.03, (200, 30, 30), 0)
    room = _lattice(distance_m + 3.0, (-4.0, 4.0), (0.0, 2.6), 0.03, (30, 30, 200), 1, seed=1)
    out = _render("visibility", IndexedCloud(PointCloud.concatenate([near, room])))
    depth, hole = out.depth_m[0], out.hole_mask[0]
    border = np.ones(hole.shape, bool)
    border[8:-8, 8:-8] = False
    leak = (~hole & (depth > distance_m + LEAK_M))[border].mean()
    assert leak <= 0.002, leak
    assert hole[border].mean() <= 0.005, hole[border].mean()
    assert (out.labels[0][border & ~hole] == 0).all()


def test_a_sparsely_sampled_wall_a_quarter_metre_away_has_no_holes():
    # Points 20 px apart (4 cm at 0.25 m, as a door frame the tours saw only obliquely): the
    # footprints (capped at 24 px) enclose every pixel, but many lie farther than 32 px from
    # a cell holding a surfel of the wall: filling from up to 64 px cells (fill_levels 6)
    # closes them (measured with 32 px cells: 5 % holes).
    near = _lattice(0.25, (-1.5, 1.5), (0.0, 2.6), 0.04, (200, 30, 30), 0)
    room = _lattice(3.25, (-4.0, 4.0), (0.0, 2.6), 0.03, (30, 30, 200), 1, seed=1)
    out = _render("visibility", IndexedCloud(PointCloud.concatenate([near, room])))
    hole = out.hole_mask[0]
    assert hole.mean() <= 0.002, hole.mean()
    assert (out.labels[0][~hole] == 0).mean() >= 0.99


def test_labels_and_colour_follow_the_visible_wall(wall_half_a_metre_away):
    out = _render("visibility", wall_half_a_metre_away)
    seen = ~out.hole_mask[0]
    assert (out.labels[0][seen] == 0).mean() > 0.99
    assert (out.rgb[0][seen][:, 2] < 60).mean() > 0.99  # red wall, not the blue room behind


def test_a_doorway_stays_open_and_edges_stay_sharp():
    # A wall 2 m ahead with a 0.6 m doorway and nothing behind it: the doorway must stay a hole
    # (no surface invented across it), and the wall's edge must not grow by more than a few px.
    left = _lattice(2.0, (-3.0, -0.3), (0.0, 2.6), 0.03, (120, 120, 120), 0)
    right = _lattice(2.0, (0.3, 3.0), (0.0, 2.6), 0.03, (120, 120, 120), 0, seed=2)
    out = _render("visibility", IndexedCloud(PointCloud.concatenate([left, right])))
    hole = out.hole_mask[0]
    edge_px = 0.3 / 2.0 * CAM.fx  # the doorway spans +-19 px around the centre column
    c = int(CAM.cx)
    door = hole[60:200, c - int(edge_px) + 4 : c + int(edge_px) - 4]
    assert door.all()
    wall = hole[60:200, : c - int(edge_px) - 2]
    assert wall.mean() < 0.02


def test_a_near_object_does_not_spread_over_the_background():
    # A 0.4 m square 1 m ahead in front of a wall 3 m ahead, both sparse: outside the square's
    # silhouette (plus its footprint) the wall shows, at its own depth.
    box = _lattice(1.0, (-0.2, 0.2), (1.05, 1.45), 0.02, (250, 250, 0), 0)
    wall = _lattice(3.0, (-4.0, 4.0), (0.0, 2.6), 0.03, (0, 0, 250), 1, seed=3)
    out = _render("visibility", IndexedCloud(PointCloud.concatenate([box, wall])))
    depth, labels = out.depth_m[0], out.labels[0]
    half_px = 0.2 / 1.0 * CAM.fx  # 25.6 px
    c = int(CAM.cx)
    inner = slice(c - int(half_px) + 3, c + int(half_px) - 3)
    assert np.allclose(depth[inner, inner], 1.0, atol=0.03) and (labels[inner, inner] == 0).all()
    margin = int(half_px) + 6  # the box's footprint is ~3 px at 1 m
    ring = np.ones_like(depth, bool)
    ring[c - margin : c + margin, c - margin : c + margin] = False
    ring &= ~out.hole_mask[0]
    assert (np.abs(depth[ring] - 3.0) < 0.3).mean() > 0.99 and (labels[ring] == 1).mean() > 0.99


@pytest.mark.parametrize("scene", ["room", "wall", "sided room"])
def test_numpy_and_torch_agree_in_visibility_mode(room_index, room_index_sided, wall_half_a_metre_away, scene):
    """Tolerance: the front-layer sums are float64 in numpy and float32 in torch, so mean depths
    differ in the last bits and a footprint radius or a depth test right at its threshold can
    flip: at most 0.2 % of the pixels may differ in hole, label or colour (> 2 levels), and depth
    agrees within 1 mm elsewhere."""
    if scene != "wall":
        index = room_index if scene == "room" else room_index_sided
        views = [ViewPose(position_m=pos, heading_rad=h, pitch_rad=p) for pos, h, p in scenes.room_view_poses(3, seed=5)]
    else:
        index = wall_half_a_metre_away
        views = [ViewPose(position_m=(0.0, 0.0, 0.0), heading_rad=h) for h in (0.0, 0.4)]
    a = RENDERERS.create("numpy", {"mode": "visibility"}).render(index, views, CAM)
    b = RENDERERS.create("torch", {"mode": "visibility", "device": "cpu"}).render(index, views, CAM)
    n = a.hole_mask.size
    assert (a.hole_mask != b.hole_mask).sum() <= 0.002 * n
    both = ~a.hole_mask & ~b.hole_mask
    assert (np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max(axis=-1)[both] > 2).sum() <= 0.002 * n
    assert (a.labels[both] != b.labels[both]).sum() <= 0.002 * n
    assert np.quantile(np.abs(a.depth_m[both] - b.depth_m[both]), 0.998) < 1e-3


def test_point_spacing_follows_the_sampling():
    coarse = _lattice(1.0, (0.0, 1.0), (0.0, 1.0), 0.04, (0, 0, 0), 0, jitter_m=0.0)
    fine = _lattice(3.0, (0.0, 1.0), (0.0, 1.0), 0.01, (0, 0, 0), 0, jitter_m=0.0)
    sp = visibility.point_spacing(np.concatenate([coarse.xyz, fine.xyz]))
    assert np.median(sp[: len(coarse)]) == pytest.approx(0.04, rel=0.1)
    assert np.median(sp[len(coarse) :]) == pytest.approx(0.01, rel=0.1)


def test_spacing_and_normals_from_one_query_match_the_separate_ones():
    wall = _lattice(1.0, (0.0, 1.0), (0.0, 1.0), 0.02, (0, 0, 0), 0, jitter_m=0.002)
    floor = PointCloud(wall.xyz[:, [1, 2, 0]] * [1.0, 1.0, 0.0], wall.rgb)  # z = 0: normal +-z
    xyz = np.concatenate([wall.xyz, floor.xyz])
    spacing, normals = visibility.point_spacing_and_normals(xyz, 4, 10)
    assert np.array_equal(spacing, visibility.point_spacing(xyz, 4))
    assert np.array_equal(normals, visibility.point_normals(xyz, 10))
    # Solved a few points at a time or all at once: each point's normal is its own, to the bit.
    for chunk in (7, len(xyz)):
        assert visibility.point_spacing_and_normals(xyz, 4, 10, chunk=chunk)[1].tobytes() == normals.tobytes()
    inner = (np.abs(xyz[:, 2] - 0.5) < 0.4) & (np.abs(xyz[:, 1] - 0.5) < 0.4)
    assert np.quantile(np.abs(normals[: len(wall)][inner[: len(wall)], 0]), 0.01) > 0.95  # the wall faces x
    assert np.quantile(np.abs(normals[len(wall) :, 2]), 0.01) > 0.95  # the floor faces z


def test_an_index_of_the_same_points_with_view_dirs_shares_their_spacing_and_normals():
    wall = _lattice(1.0, (0.0, 1.0), (0.0, 1.0), 0.02, (0, 0, 0), 0)
    plain = IndexedCloud(wall)
    dirs = quantise_view_dirs(np.tile([[-1.0, 0.0, 0.0]], (len(wall), 1)))
    sided = IndexedCloud(PointCloud(wall.xyz, wall.rgb, wall.labels, wall.label_names, dirs))
    assert share_point_geometry(plain, sided) == 0  # nothing computed yet, nothing shared
    normals = point_normals_of(plain, 10, 4)
    assert share_point_geometry(plain, sided) == 3  # the tree, the spacing and the normals
    assert point_normals_of(sided, 10, 4) is normals and point_spacing_of(sided, 4) is point_spacing_of(plain, 4)
    assert point_tree_of(sided) is point_tree_of(plain)
    # ... and they are what the sided index would have computed itself.
    alone = IndexedCloud(PointCloud(wall.xyz, wall.rgb, wall.labels, wall.label_names, dirs))
    assert np.array_equal(point_normals_of(alone, 10, 4), normals)
    assert np.array_equal(point_spacing_of(alone, 4), point_spacing_of(plain, 4))
    # Other points, or the same ones in another order, get nothing.
    with pytest.raises(ValueError, match="same points"):
        share_point_geometry(plain, IndexedCloud(wall, seed=1))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_spacing_of_a_cloud_smaller_than_the_neighbourhood_is_finite(n):
    # A one-point map averaged an empty slice (NaN radius) and the torch renderer then indexed
    # its radius table with NaN; too few neighbours must mean isolated points (the upper clip),
    # exactly as point_spacing's padded query says.
    xyz = np.arange(3 * n, dtype=np.float64).reshape(n, 3) * 0.01
    spacing, normals = visibility.point_spacing_and_normals(xyz, 4, 10)
    assert np.isfinite(spacing).all() and np.array_equal(spacing, visibility.point_spacing(xyz, 4))
    assert normals.shape == (n, 3)


def test_a_wall_seen_along_a_corridor_is_not_its_own_occluder():
    # A wall 0.6 m to the left running from 0.3 m to 6 m ahead, and an end wall at 6.5 m: seen at
    # grazing angles, the wall's nearer footprints must not remove (or leave holes in) its farther
    # pixels, and the end wall must not show through it.
    side = _lattice(0.6, (0.3, 6.0), (0.0, 2.6), 0.025, (200, 30, 30), 0)
    side = PointCloud(side.xyz[:, [1, 0, 2]].copy(), side.rgb, side.labels, side.label_names)
    end = _lattice(6.5, (-3.0, 3.0), (0.0, 2.6), 0.025, (30, 30, 200), 1, seed=4)
    out = _render("visibility", IndexedCloud(PointCloud.concatenate([side, end])))
    # Where the wall is in the image (camera axes: x right = world -y, y down, z ahead).
    vv, uu = np.mgrid[0 : CAM.height_px, 0 : CAM.width_px].astype(float)
    x, y = (uu - CAM.cx) / CAM.fx, (vv - CAM.cy) / CAM.fy
    with np.errstate(divide="ignore"):
        z = np.where(x < 0, -0.6 / x, np.inf)
    height = 1.25 - y * z
    wall = (z > 0.35) & (z < 5.5) & (height > 0.05) & (height < 2.55)
    wall[:, int(CAM.cx) - 3 :] = False  # the far end, a few pixels wide, where the wall meets the end wall
    assert (out.hole_mask[0][wall]).mean() <= 0.02
    assert (out.labels[0][wall & ~out.hole_mask[0]] == 0).mean() >= 0.99
    seen = wall & ~out.hole_mask[0]
    assert np.quantile(np.abs(out.depth_m[0][seen] - z[seen]) / z[seen], 0.99) < 0.1


def test_colour_filter_removes_sampling_noise_but_not_edges():
    # A grey wall 3 m away whose points carry +-40 levels of noise (one sample per pixel there):
    # the 3x3 reconstruction filter over the same surface lowers the pixel noise; a red square
    # 1 m ahead keeps pure red inside its silhouette (no blend across the depth edge).
    wall = _lattice(3.0, (-4.0, 4.0), (0.0, 2.6), 0.025, (128, 128, 128), 1, seed=4)
    rng = np.random.default_rng(5)
    wall.rgb[:] = np.clip(128 + rng.normal(0, 40, (len(wall), 1)), 0, 255).astype(np.uint8)
    box = _lattice(1.0, (-0.2, 0.2), (1.05, 1.45), 0.01, (250, 0, 0), 0)
    index = IndexedCloud(PointCloud.concatenate([box, wall]))
    on = _render("visibility", index)
    off = _render("visibility", index, colour_filter_rel=0.0)
    far = (np.abs(on.depth_m[0] - 3.0) < 0.2) & ~on.hole_mask[0]
    noise_on, noise_off = on.rgb[0][far][:, 0].std(), off.rgb[0][far][:, 0].std()
    assert noise_on < noise_off / 1.5, (noise_on, noise_off)
    near = (np.abs(on.depth_m[0] - 1.0) < 0.05) & ~on.hole_mask[0]
    assert near.sum() > 1000 and (on.rgb[0][near][:, 1] == 0).all()  # no grey from the wall behind


def _two_faced_wall(near_x_m: float, length_m: float = 8.0, along: bool = False) -> IndexedCloud:
    """A wall between two rooms as the agent-built maps hold it: two faces 10 cm apart
    (libs/world/house.py, 5 cm per room), each sampled like the rgbd map (2.6 cm),
    the near one red (label 0), the far one blue (label 1). ``along``: the wall runs along the
    view direction at ``near_x_m`` to the left (a corridor), else it faces the camera."""
    span = (0.3, 0.3 + length_m) if along else (-length_m / 2, length_m / 2)
    faces = [_lattice(near_x_m, span, (0.0, 2.6), 0.026, (200, 30, 30), 0),
             _lattice(near_x_m + 0.1, span, (0.0, 2.6), 0.026, (30, 30, 200), 1, seed=1)]
    if along:
        faces = [PointCloud(f.xyz[:, [1, 0, 2]].copy(), f.rgb, f.labels, f.label_names) for f in faces]
    return IndexedCloud(PointCloud.concatenate(faces))


@pytest.mark.parametrize("distance_m", [2.0, 3.0])
def test_the_far_face_of_a_wall_does_not_show_through_its_near_face(distance_m):
    # Issue 20: with the flat tolerance (4 cm + 3 % of the depth, more than the 10 cm between the
    # faces beyond 2 m) the far face filled the near face's sampling gaps: measured 6.7 % of the
    # wall's pixels at 2 m and 18 % at 3 m (speckle on the dashboard, SSIM 0.83 at the planner's
    # candidates). The slope-scaled tolerance keeps a face-on wall within ~3 cm.
    out = _render("visibility", _two_faced_wall(distance_m))
    seen = ~out.hole_mask[0]
    assert seen.mean() > 0.3
    assert (out.labels[0][seen] == 1).mean() <= 0.002
    assert (np.abs(out.depth_m[0][seen] - distance_m) < 0.05).mean() >= 0.998


def test_a_two_faced_wall_along_a_corridor_shows_its_near_face_without_holes():
    # Seen at grazing angles the near face changes depth by up to ~0.2 m per pixel (8 m away):
    # the tolerance must follow that slope (or the face removes its own farther surfels), and
    # the far face, 10 / cos(angle) cm behind, must still stay hidden.
    out = _render("visibility", _two_faced_wall(0.6, along=True))
    vv, uu = np.mgrid[0 : CAM.height_px, 0 : CAM.width_px].astype(float)
    x, y = (uu - CAM.cx) / CAM.fx, (vv - CAM.cy) / CAM.fy
    with np.errstate(divide="ignore"):
        z = np.where(x < 0, -0.6 / x, np.inf)
    height = 1.25 - y * z
    wall = (z > 0.35) & (z < 7.5) & (height > 0.05) & (height < 2.55)
    seen = wall & ~out.hole_mask[0]
    assert out.hole_mask[0][wall].mean() <= 0.02
    assert (out.labels[0][seen] == 0).mean() >= 0.99
    assert np.quantile(np.abs(out.depth_m[0][seen] - z[seen]) / z[seen], 0.99) < 0.1


def _grazing_plane(h: int, w: int, focal_px: float, seed: int = 0):
    """The front layer of a wall 0.6 m to the left of the camera, running from 0.3 to 6 m
    ahead (camera axes: x = -0.6 m), one point per pixel at a random sub-pixel position, each with
    its own colour; and the mask of the pixels it covers. Its depth slope per pixel is exact:
    z^2 |n_x| / (f |d|) for the plane n . X = d, capped at 80 degrees as the renderer caps it."""
    rng = np.random.default_rng(seed)
    hp, wp = h + 2, w + 2
    cols = np.arange(wp, dtype=np.float64)[None, :] - 1 + rng.uniform(-0.5, 0.5, (hp, wp))
    xi = (cols - (w - 1) / 2) / focal_px
    with np.errstate(divide="ignore"):
        z = np.where(xi < 0, -0.6 / xi, np.inf)
    on = (z > 0.3) & (z < 6.0)  # 86 degrees at the far end
    zmin = np.where(on, z, np.inf).astype(np.float32)
    slope = z / focal_px * np.minimum(z / 0.6, np.tan(np.radians(80.0)))
    colour = rng.integers(0, 256, (3, hp, wp)).astype(np.float32)
    front = visibility.FrontLayer(
        zmin=zmin, count=on.astype(np.float32), sum_z=np.where(on, zmin, 0).astype(np.float32),
        sum_rgb=[np.where(on, c, 0).astype(np.float32) for c in colour],
        sum_spacing=np.where(on, 0.026, 0).astype(np.float32), label=None,
        sum_slope=np.where(on, slope, 0).astype(np.float32))
    return front, on[1:-1, 1:-1], colour[:, 1:-1, 1:-1]


@pytest.mark.parametrize("compiled", [False, True])
def test_a_grazing_wall_keeps_every_surfel_with_the_slope_scaled_tolerance(compiled):
    from libs.pointrender.ops_numpy import _NumpyOps

    h = w = 128
    front, on, colour = _grazing_plane(h, w, 64.0)
    params = visibility.VisibilityParams(
        focal_px=64.0, footprint_scale=2.0, max_radius_px=24, min_radius_px=1, gap_levels=5, fill_levels=5,
        gap_max_m=0.08, tol_rel1=1.005, tol_abs_m=0.02, slope_per_px=np.tan(np.radians(60.0)) / 64.0,
        slope_px=1.0)

    def kept(p):
        """Share of the wall's pixels that show their own surfel (a removed one is filled from
        the pyramid, a mean of several colours, or left a hole)."""
        compose = visibility.compose_compiled if compiled else (lambda *a: visibility.compose(_NumpyOps(), *a))
        rgb, _, hole, _ = compose(front, p, h, w)
        own = (np.abs(np.asarray(rgb) - colour) < 0.5).all(axis=0) & ~hole
        return own[on].mean()

    assert kept(params) == 1.0
    # Without the slope term the same tolerance removes a wall's own farther surfels (measured:
    # 12-34 % of them on a sampled wall, by depth): this scene tells the two apart.
    from dataclasses import replace

    assert kept(replace(params, slope_px=0.0)) < 0.95


def _seen_from(cloud: PointCloud, direction) -> PointCloud:
    """``cloud`` as the reconstructor leaves it when every point was seen from ``direction``."""
    unit = np.tile(np.asarray(direction, float) / np.linalg.norm(direction), (len(cloud), 1))
    return PointCloud(cloud.xyz, cloud.rgb, cloud.labels, cloud.label_names, quantise_view_dirs(unit))


def _wall_between_rooms(near_face: bool) -> IndexedCloud:
    """A wall between this room (x < 2) and the next (x > 2.1), seen as the robot mapped it: the
    next room's face (blue, label 1) from the next room, its far wall (green) from inside it, and
    this room's face (red, label 0) only with ``near_face``."""
    parts = [_seen_from(_lattice(2.1, (-4.0, 4.0), (0.0, 2.6), 0.026, (30, 30, 200), 1, seed=1), (1, 0, 0)),
             _seen_from(_lattice(5.0, (-4.0, 4.0), (0.0, 2.6), 0.026, (30, 200, 30), 1, seed=2), (-1, 0, 0))]
    if near_face:
        parts.append(_seen_from(_lattice(2.0, (-4.0, 4.0), (0.0, 2.6), 0.026, (200, 30, 30), 0), (-1, 0, 0)))
    return IndexedCloud(PointCloud.concatenate(parts))


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_a_wall_face_never_mapped_shows_as_unseen_not_in_the_next_rooms_paint(backend):
    # The weakness the issue-20 screenshots showed: where this room's face of a wall was never
    # mapped, the view showed its other face, the neighbouring room's paint 10 cm behind. A map
    # that records where its points were seen from draws that face in the unknown grey, at the
    # wall's depth (it still hides the room behind), with its label.
    index = _wall_between_rooms(near_face=False)
    out = _render("visibility", index, backend)
    seen = ~out.hole_mask[0]
    assert seen.mean() > 0.5
    assert (out.rgb[0][seen] == 128).all(axis=-1).mean() >= 0.99
    assert (np.abs(out.depth_m[0][seen] - 2.1) < 0.05).mean() >= 0.99
    assert (out.labels[0][seen] == 1).mean() >= 0.99
    # Without the record (or with the test off) the next room's blue shows: what this test guards.
    plain = _render("visibility", index, backend, unseen_side=False)
    assert (plain.rgb[0][~plain.hole_mask[0]][:, 2] == 200).mean() > 0.9


def test_a_noisy_wall_face_never_mapped_shows_as_unseen_by_its_neighbours_vote():
    # Issue 33: on a depth-noise map the next room's face is a slab a few cm thick, and ten of its
    # points' normal tilts anywhere within it; decided point by point, the face this room never
    # mapped is a mottle of grey and the next room's blue. Decided by a vote of each point's
    # neighbours, it is evenly grey again.
    face = _lattice(2.1, (-4.0, 4.0), (0.0, 2.6), 0.026, (30, 30, 200), 1, seed=1)
    xyz = face.xyz + np.random.default_rng(3).normal(0.0, 0.03, (len(face), 1)) * [1.0, 0.0, 0.0]
    noisy = _seen_from(PointCloud(xyz, face.rgb, face.labels, face.label_names), (1, 0, 0))
    far = _seen_from(_lattice(5.0, (-4.0, 4.0), (0.0, 2.6), 0.026, (30, 200, 30), 1, seed=2), (-1, 0, 0))
    index = IndexedCloud(PointCloud.concatenate([noisy, far]))

    def grey_and_blue(**cfg) -> tuple[float, float]:
        out = _render("visibility", index, **cfg)
        seen = ~out.hole_mask[0]
        assert seen.mean() > 0.5
        rgb = out.rgb[0][seen]
        return float((rgb == 128).all(axis=-1).mean()), float((rgb[:, 2] >= 150).mean())

    grey, blue = grey_and_blue(side_vote_neighbours=0)
    assert grey < 0.8 and blue > 0.05  # the mottle the vote is for
    grey, blue = grey_and_blue()  # the default vote
    assert grey >= 0.99 and blue < 0.01


def test_the_side_vote_keeps_a_clean_sided_wall_and_cancels_on_a_thin_panel_seen_from_both_sides():
    wall = _lattice(2.0, (-1.0, 1.0), (0.0, 1.0), 0.026, (200, 30, 30), 0)
    normals = np.tile(np.float32([1.0, 0.0, 0.0]), (len(wall), 1))
    # A clean wall, every point sided: the vote keeps each side and normal.
    n, sided = visibility.vote_sides(wall.xyz, normals, np.ones(len(wall), np.uint8), 16, 0.5)
    assert sided.all() and np.allclose(n, normals, atol=1e-6)
    # Half of its points oriented one way and half the other (a panel whose two faces coincide):
    # the votes cancel, no side is known.
    flip = np.where((np.arange(len(wall)) % 2 == 0)[:, None], normals, -normals)
    _, sided = visibility.vote_sides(wall.xyz, flip, np.ones(len(wall), np.uint8), 16, 0.5)
    assert not sided.any()
    # Points without a side of their own do not vote: a wall a fifth of whose points are sided has none.
    few = (np.arange(len(wall)) % 5 == 0).astype(np.uint8)
    _, sided = visibility.vote_sides(wall.xyz, normals, few, 16, 0.5)
    assert not sided.any()


def test_a_mapped_near_face_and_a_surface_seen_from_both_sides_keep_their_colour():
    out = _render("visibility", _wall_between_rooms(near_face=True))
    seen = ~out.hole_mask[0]
    assert seen.mean() > 0.5 and (out.rgb[0][seen][:, 0] == 200).mean() >= 0.99
    # A thin panel seen from both sides as often: fusion averaged its cameras' directions to a
    # short vector, nearly in its plane (here 0.05 across it, 0.5 along it): no side is known.
    panel = _lattice(1.5, (-1.0, 1.0), (0.5, 2.0), 0.02, (200, 30, 30), 0)
    across = np.where(np.arange(len(panel)) % 2 == 0, 0.05, -0.05)
    mean_dirs = np.column_stack([across, np.zeros(len(panel)), np.full(len(panel), 0.5)])
    both = PointCloud(panel.xyz, panel.rgb, panel.labels, panel.label_names, quantise_view_dirs(mean_dirs))
    out = _render("visibility", IndexedCloud(both))
    seen = ~out.hole_mask[0]
    assert seen.mean() > 0.2 and (out.rgb[0][seen][:, 0] == 200).mean() >= 0.99


@pytest.mark.skipif(not visibility_kernels.AVAILABLE, reason="needs numba")
def test_the_compiled_visibility_pass_has_one_signature_for_every_path_into_it():
    # The renderer's front layer (strided views of the kernel's rows, an int32 nearest-point image), with
    # and without labels and the slope term, and contiguous arrays with an int64 label image (the array
    # code's): one machine code for all, not one per layout and dtype (each 3.5 s of CPU to compile).
    index = _wall_and_room(1.0)
    for cfg in ({}, {"visibility_slope_px": 0.0}):
        r = RENDERERS.create("numpy", {"mode": "visibility", **cfg})
        for labelled in (True, False):
            out = r.render(index, [ViewPose(position_m=(0.0, 0.0, 0.0))], PinholeCamera(64, 64, 90.0),
                         with_labels=labelled)
            assert (~out.hole_mask[0]).mean() > 0.99
    h = w = 32
    front, on, _ = _grazing_plane(h, w, 32.0)
    front.label = np.where(np.isfinite(front.zmin), 1, -1).astype(np.int64)
    params = visibility.VisibilityParams(focal_px=32.0, footprint_scale=2.0, max_radius_px=8, min_radius_px=1,
                                         gap_levels=3, fill_levels=3, gap_max_m=0.08, tol_rel1=1.005, tol_abs_m=0.02)
    _, _, hole, labels = visibility.compose_compiled(front, params, h, w)
    assert (labels[on & ~hole] == 1).all()
    assert len(visibility_kernels.finish.signatures) == 1, visibility_kernels.finish.signatures
    assert len(visibility_kernels.classes.signatures) == 1, visibility_kernels.classes.signatures
