"""Occlusion culling (:mod:`libs.pointrender.occlusion`) skips blocks wholly behind the near
surfaces and leaves every pixel as drawing them does."""

from __future__ import annotations

import numpy as np
import pytest

from services.renderer.tools import scenes
from shared.cloud import PointCloud
from shared.geometry import PinholeCamera, camera_pose
from libs.pointrender import RENDERERS, IndexedCloud, kernels

from .test_renderer_visibility import _lattice

needs_numba = pytest.mark.skipif(not kernels.AVAILABLE, reason="occlusion culling runs on the compiled path")
CAM = PinholeCamera(200, 150, 90.0)  # not square: rows and columns must not be swapped


def _both(index, poses, **cfg):
    on = RENDERERS.create("numpy", {"occlusion_cull": True, "occlusion_min_points": 0, **cfg})
    off = RENDERERS.create("numpy", {"occlusion_cull": False, **cfg})
    return on.render_poses(index, poses, CAM), off.render_poses(index, poses, CAM)


def _identical(a, b):
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("rgb", "depth_m", "hole_mask", "labels"))


@needs_numba
# Near distances at which this flat has blocks to cull: few (its two rooms are small, most blocks
# are seen), and fewer since the guard band (covers now span 16 px past the image border, where a
# quadrant reaching past them reads +inf and proves nothing): at 3 m none is left.
@pytest.mark.parametrize("near_m", [4.0, 5.0])
def test_culling_changes_no_pixel_of_the_built_flat(room_index, near_m):
    poses = [camera_pose(pos, h, p) for pos, h, p in scenes.room_view_poses(8, seed=21)]
    poses.append(camera_pose((4.0, 3.0, 0.0), 0.3, 0.0))  # standing in a wall
    on, off = _both(room_index, poses, occlusion_near_m=near_m)
    assert _identical(on, off)
    # ... and it did cull (a few blocks: this flat's two rooms are small, most blocks are seen).
    assert sum(on.visible_points) < sum(off.visible_points), (on.visible_points, off.visible_points)
    # The occluder's classes and the visibility pass's were bucketed by one compiled signature.
    from libs.pointrender import visibility_kernels

    assert len(visibility_kernels.bucket.signatures) == 1, visibility_kernels.bucket.signatures


@needs_numba
def test_culling_keeps_what_a_doorway_shows():
    # A two-faced wall 2 m ahead with a 0.8 m doorway, a room 3 m behind it: the room's blocks
    # seen through the doorway are drawn, those behind the wall are not, and no pixel changes.
    wall = [_lattice(2.0, (-4.0, -0.4), (0.0, 2.6), 0.026, (200, 30, 30), 0),
            _lattice(2.0, (0.4, 4.0), (0.0, 2.6), 0.026, (200, 30, 30), 0, seed=2),
            _lattice(2.1, (-4.0, -0.4), (0.0, 2.6), 0.026, (200, 30, 30), 0, seed=3),
            _lattice(2.1, (0.4, 4.0), (0.0, 2.6), 0.026, (200, 30, 30), 0, seed=4)]
    room = _lattice(5.0, (-6.0, 6.0), (0.0, 2.6), 0.026, (30, 30, 200), 1, seed=5)
    index = IndexedCloud(PointCloud.concatenate([*wall, room]))
    poses = [camera_pose((0.0, 0.0, 0.0), h, 0.0) for h in (0.0, 0.3, -0.5)]
    # At 2 px cells: at the default 2.5 the view draws coarser levels, and the footprint class a
    # farther block's surfels may reach (bounded from the largest spacing drawn) is no longer below
    # the occluder's largest class, as the proof requires: nothing is culled (exact, but it shows
    # nothing of the culling).
    on, off = _both(index, poses, lod_cell_px=2.0)
    assert _identical(on, off)
    assert (on.labels[0] == 1).sum() > 500  # the room shows through the doorway
    assert sum(on.visible_points) < sum(off.visible_points)
