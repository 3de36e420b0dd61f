"""Anticipated views at the candidate's own floor height (stairs, another storey), and the map id."""

from __future__ import annotations

import numpy as np
import pytest

from services.renderer.core import MapRenderer, SpatialMapper
from services.renderer.core.errors import MapMismatchError
from services.renderer.core.floors import FloorHeights
from shared.cloud import PointCloud
from libs.pointrender import RENDERERS, IndexedCloud
from shared.schemas import CameraIntrinsics, ViewPose

RISE_M, RUN_M, STEPS = 0.17, 0.28, 10  # a staircase from x = 2 m up to 1.7 m, then a landing


def _surface(x0, x1, y0, y1, z, step=0.03, colour=(150, 150, 150), label=0):
    xs, ys = np.arange(x0, x1, step), np.arange(y0, y1, step)
    xx, yy = np.meshgrid(xs, ys)
    n = xx.size
    return PointCloud(np.column_stack([xx.ravel(), yy.ravel(), np.full(n, z)]),
                      np.tile(np.array(colour, np.uint8), (n, 1)), np.full(n, label, np.int32))


def _house() -> IndexedCloud:
    parts = [_surface(0.0, 2.0, 0.0, 1.2, 0.0, label=0)]  # ground floor
    for k in range(STEPS):  # treads (and risers, so the stairs are closed)
        x0 = 2.0 + k * RUN_M
        parts.append(_surface(x0, x0 + RUN_M, 0.0, 1.2, (k + 1) * RISE_M, label=1))
        riser = np.stack(np.meshgrid(np.arange(0.0, 1.2, 0.03), np.arange(k * RISE_M, (k + 1) * RISE_M, 0.03)), -1)
        riser = riser.reshape(-1, 2)
        parts.append(PointCloud(np.column_stack([np.full(len(riser), x0), riser[:, 0], riser[:, 1]]),
                                np.full((len(riser), 3), 90, np.uint8), np.full(len(riser), 1, np.int32)))
    top = 2.0 + STEPS * RUN_M
    parts.append(_surface(top, top + 2.0, 0.0, 1.2, STEPS * RISE_M, label=2))  # upper landing
    parts.append(_surface(0.0, top + 2.0, 0.0, 1.2, STEPS * RISE_M + 2.5, label=3))  # ceiling over all
    return IndexedCloud(PointCloud.concatenate(parts))


def test_floor_under_a_stair_tread_and_on_the_landing():
    index = _house()
    floors = FloorHeights(index.cloud.xyz)
    for k in (2, 5, 7):  # treads 0.51, 1.02 and 1.36 m above the agent's floor
        x = 2.0 + (k + 0.5) * RUN_M
        assert floors.floor_z(x, 0.6, 0.0, 1.5) == pytest.approx((k + 1) * RISE_M, abs=0.02), k
    # From the agent's floor near the top of the stairs the landing is found, and the ground floor
    # stays the ground floor (it is the standing surface nearest the hint there).
    landing_x = 2.0 + STEPS * RUN_M + 1.0
    assert floors.floor_z(landing_x, 0.6, 1.4, 1.5) == pytest.approx(STEPS * RISE_M, abs=0.02)
    assert floors.floor_z(1.0, 0.6, 0.0, 1.5) == pytest.approx(0.0, abs=0.02)
    # No standing surface within range: the height asked for is kept.
    assert floors.floor_z(landing_x, 0.6, -3.0, 0.5) == -3.0
    # A column with no points of its own (the floor under the robot) takes its neighbours'.
    assert floors.floor_z(50.0, 50.0, 0.3, 1.5) == 0.3


def test_a_candidate_on_the_stairs_is_rendered_at_its_own_height():
    index = _house()
    renderer = RENDERERS.create("numpy")
    port = MapRenderer(index, renderer, SpatialMapper())
    cam = CameraIntrinsics(width_px=96, height_px=96)
    x = 2.0 + 4.5 * RUN_M  # on the fifth tread, 0.85 m up
    agent_z = 0.0
    out = port.views("m", [ViewPose(position_m=(x, 0.6, agent_z), heading_rad=0.0)], cam)
    own = renderer.render(index, [ViewPose(position_m=(x, 0.6, 5 * RISE_M), heading_rad=0.0)], cam)
    low = renderer.render(index, [ViewPose(position_m=(x, 0.6, agent_z), heading_rad=0.0)], cam)
    assert np.array_equal(out.rgb, own.rgb) and np.array_equal(out.depth_m, own.depth_m)
    assert not np.array_equal(out.depth_m, low.depth_m)  # the agent's height would look elsewhere
    # floor_search_m = 0 keeps the height as given.
    kept = port.views("m", [ViewPose(position_m=(x, 0.6, agent_z))], cam, floor_search_m=0.0)
    assert np.array_equal(kept.depth_m, low.depth_m)


def test_a_bound_map_renderer_refuses_another_map_id():
    index = _house()
    port = MapRenderer(index, RENDERERS.create("numpy"), SpatialMapper(), map_id="house", version=3)
    view = [ViewPose(position_m=(1.0, 0.6, 0.0))]
    cam = CameraIntrinsics(width_px=32, height_px=32)
    assert port.views("house", view, cam).map_id == "house"
    with pytest.raises(MapMismatchError):
        port.views("other", view, cam)
    # Unbound (in-process) ports answer under the id they are asked for.
    free = MapRenderer(index, RENDERERS.create("numpy"), SpatialMapper())
    assert free.views("anything", view, cam).map_id == "anything"
