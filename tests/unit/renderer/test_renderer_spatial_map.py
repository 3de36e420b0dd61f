"""The top-down spatial map: occupancy classes, overlays, orientation, caching."""

from __future__ import annotations

import math

import numpy as np

from services.renderer.core import SpatialMapper
from services.renderer.core.spatial_map import FREE, OBSTACLE, UNKNOWN
from shared.cloud import PointCloud
from libs.pointrender import IndexedCloud
from shared.schemas import Candidate, CandidateKind, Pose


def _grid_cloud() -> IndexedCloud:
    """Floor over x, y in [0, 4] except a never-seen patch x, y in [3, 4]; a 1 m box (obstacle) at
    x, y in [1, 2]; a ceiling at 2.6 m (not an obstacle); an upper floor 3 m up over x in [0, 1]."""
    rng = np.random.default_rng(0)
    floor = rng.uniform(0, 4, size=(200_000, 2))
    floor = floor[~((floor[:, 0] > 3) & (floor[:, 1] > 3))]
    box = np.column_stack([rng.uniform(1, 2, 30_000), rng.uniform(1, 2, 30_000), rng.uniform(0, 1, 30_000)])
    ceiling = np.column_stack([rng.uniform(0, 4, (50_000, 2)), np.full(50_000, 2.6)])
    upper = np.column_stack([rng.uniform(0, 1, (20_000, 2)), np.full(20_000, 3.0)])
    xyz = np.concatenate([np.column_stack([floor, np.zeros(len(floor))]), box, ceiling, upper])
    labels = np.concatenate([np.where(floor[:, 0] < 2, 0, 1), np.full(len(box) + len(ceiling) + len(upper), 2)])
    cloud = PointCloud(xyz, np.full((len(xyz), 3), 128, np.uint8), labels.astype(np.int32),
                       {0: "kitchen floor", 1: "hall floor", 2: "stuff"})
    return IndexedCloud(cloud)


def test_occupancy_classes():
    index = _grid_cloud()
    grid = SpatialMapper().grid(index, 0.0)

    def cell(x, y):
        r, c = grid.world_to_cell(np.array([[x, y]]))[0]
        return grid.cells[r, c]

    assert cell(0.5, 0.5) == FREE and cell(2.5, 0.5) == FREE  # floor under the ceiling is free
    assert cell(1.5, 1.5) == OBSTACLE
    assert cell(3.5, 3.5) == UNKNOWN  # nothing seen there
    assert cell(-0.3, 2.0) == UNKNOWN  # the margin around the map
    names = {name for name, _, _ in grid.rooms}
    assert names == {"kitchen", "hall"}
    kitchen = next((x, y) for n, x, y in grid.rooms if n == "kitchen")
    assert 0 < kitchen[0] < 2 and 0 < kitchen[1] < 4
    # From the upper floor (z = 3) the ground-floor box is out of the height band: no obstacle.
    upper = SpatialMapper().grid(index, 3.0)
    r, c = upper.world_to_cell(np.array([[0.5, 0.5]]))[0]
    assert upper.cells[r, c] == FREE
    assert not (upper.cells == OBSTACLE).any()


def test_grid_is_cached_per_floor():
    index = _grid_cloud()
    mapper = SpatialMapper()
    assert mapper.grid(index, 0.0) is mapper.grid(index, 0.05)
    assert mapper.grid(index, 0.0) is not mapper.grid(index, 3.0)


def _pixel(m, xy):
    return np.rint(m.world_to_px @ np.array([xy[0], xy[1], 1.0])).astype(int)


def test_drawing_places_agent_candidates_and_orientation():
    index = _grid_cloud()
    mapper = SpatialMapper()
    pose = Pose(position_m=(0.5, 2.5, 0.0), heading_rad=0.0)
    cands = [Candidate(index=0, dx_m=1.0, dy_m=0.0), Candidate(index=1, dx_m=0.0, dy_m=1.0),
             Candidate(index=2, kind=CandidateKind.STOP)]
    traj = np.array([[0.5, 0.5, 0.0], [0.5, 1.5, 0.0], [0.5, 2.5, 0.0]])
    m = mapper.draw(index, pose, traj, cands, agent_up=False, size_px=512)
    assert m.image.shape == (512, 512, 3) and m.image.dtype == np.uint8
    a = _pixel(m, (0.5, 2.5))
    assert tuple(m.image[a[1], a[0]]) == (220, 30, 30)  # agent disc
    c0 = _pixel(m, (1.5, 2.5))
    # A candidate disc is orange around its number.
    ring = m.image[c0[1] - 6 : c0[1] + 7, c0[0] - 9]
    assert (np.abs(ring.astype(int) - (255, 150, 0)).sum(axis=1) < 30).any()
    # Absolute: +y is up in the image.
    assert _pixel(m, (0.5, 3.5))[1] < a[1]

    # Agent-up, heading +x: the world +x direction points up in the image, the agent is centred.
    up = mapper.draw(index, pose, traj, cands, agent_up=True, size_px=512, radius_m=2.0)
    a2, ahead = _pixel(up, (0.5, 2.5)), _pixel(up, (1.5, 2.5))
    assert tuple(a2) == (256, 256)
    assert ahead[1] < a2[1] and abs(ahead[0] - a2[0]) <= 1
    assert abs(up.metres_per_px - 4.0 / 512) < 1e-9
    # Heading +y with agent-up: world +x now points right... of a viewer facing +y, i.e. right.
    up2 = mapper.draw(index, Pose(position_m=(0.5, 2.5, 0.0), heading_rad=math.pi / 2), agent_up=True,
                      size_px=512, radius_m=2.0)
    assert _pixel(up2, (1.5, 2.5))[0] > 256


def test_map_shows_obstacles_dark_and_unknown_grey():
    index = _grid_cloud()
    m = SpatialMapper().draw(index, Pose(position_m=(0.5, 0.5, 0.0)), size_px=512, radius_m=None)
    box = _pixel(m, (1.5, 1.5))
    unknown = _pixel(m, (3.6, 3.6))
    free = _pixel(m, (2.6, 0.6))
    assert m.image[box[1], box[0]].max() < 60
    assert tuple(m.image[unknown[1], unknown[0]]) == (120, 120, 120)
    assert m.image[free[1], free[0]].min() > 220


def test_picture_candidates_stand_in_free_space_and_do_not_face_walls(room_index, room_gt):
    from services.renderer.tools.pictures import free_space_candidates
    from shared.geometry import PinholeCamera, camera_pose

    grid = SpatialMapper().grid(room_index, 0.0)
    agent = np.array([1.5, 3.0])
    for heading in (0.0, math.pi / 2, math.pi):
        cands = free_space_candidates(grid, agent, heading)
        assert 1 <= len(cands) <= 3
        for c in cands:
            xy = agent + (c.dx_m, c.dy_m)
            r, col = grid.world_to_cell(xy)[0]
            assert grid.cells[r, col] == FREE
            # The view from the waypoint, facing away from the agent, sees at least 1 m ahead.
            _, depth, _ = room_gt.render(
                camera_pose((xy[0], xy[1], 0.0), math.atan2(c.dy_m, c.dx_m)), PinholeCamera(64, 64, 90.0))
            assert depth[32, 32] > 1.0


def test_outlined_text_is_drawn_once_with_its_halo_around_it():
    """The halo was a thicker white copy of the text, whose glyphs advance further: it drifted right
    and read as the text twice ("agentt"). Now the halo hugs the text: it ends within 2 px of it."""
    import numpy as np

    from services.renderer.core.spatial_map import _text

    img = np.full((40, 300, 3), 128, np.uint8)
    _text(img, "top-down map, agent heading up", (6, 20), 0.45, (0, 0, 0))
    dark = np.argwhere((img < 60).all(axis=2))
    light = np.argwhere((img > 200).all(axis=2))
    assert len(dark) and len(light)
    assert light[:, 1].max() <= dark[:, 1].max() + 2 and light[:, 1].min() >= dark[:, 1].min() - 2


def test_the_legend_sits_on_an_opaque_panel_at_a_legible_size():
    import numpy as np

    from services.renderer.core.spatial_map import SpatialMapper

    img = np.full((256, 256, 3), 128, np.uint8)
    SpatialMapper._legend(img, "top-down map", [("free", (230, 230, 230)), ("agent", (220, 30, 30))], 0.5)
    panel = img[8:30, 8:60]
    # White behind the text (not the grey map), and dark glyphs on it.
    assert (panel == 255).all(axis=2).mean() > 0.5 and (panel < 80).all(axis=2).any()
    assert (img[4:70, 4:100] == (220, 30, 30)).all(axis=2).any()  # the swatch


def test_a_thumbnail_map_is_drawn_without_a_legend_that_would_hide_it():
    from services.renderer.core import SpatialMapper
    from services.renderer.core.spatial_map import _LEGEND_MAX_AREA
    from shared.cloud import PointCloud
    from libs.pointrender import IndexedCloud
    from shared.schemas import Pose

    xyz = np.stack(np.meshgrid(np.arange(-2, 2, 0.05), np.arange(-2, 2, 0.05), [0.0]), -1).reshape(-1, 3)
    index = IndexedCloud(PointCloud(xyz.astype(np.float32), np.full((len(xyz), 3), 128, np.uint8)))
    pose = Pose(position_m=(0.0, 0.0, 0.0))
    small = SpatialMapper().draw(index, pose, None, [], size_px=96).image
    large = SpatialMapper().draw(index, pose, None, [], size_px=512).image
    white = lambda img: (img == 255).all(axis=2).mean()  # noqa: E731 - the legend's panel
    assert white(small) < 0.05 < white(large) < _LEGEND_MAX_AREA
