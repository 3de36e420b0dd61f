"""A robot that starts nearer to a wall than the predictor's body clearance (issue 33's boxed-in episodes).

Five of the 300 seed-0 ablation episodes (ids 126, 174, 233, 255, 258) start 0.1-0.2 m from a wall, with
furniture 0.35-0.7 m away on the other side: the simulator's agent (0.1 m radius) stands there, but the
predictor's 0.25 m disc clears no direction, so the predictor proposed nothing and the mission stopped
at step 0 on every map. Only where nothing fits at the full clearance does the predictor sweep again
with ``escape_clearance_m``; every other panorama keeps the candidates it had.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.geometry import PinholeCamera
from shared.schemas import Pose

from services.mapper.core import GeometricPredictor, GeometricPredictorConfig
from services.mapper.core.discovery import discovery_config
from services.mapper.tools.boxworld import Box, BoxWorld, BoxWorldRobot

START = (1.5, 0.1, 0.0)  # 0.1 m north of the south wall


def _alcove() -> BoxWorld:
    """A 6 x 4 m room whose south wall a 1 m high sideboard (x 0-3 m, y 0.5-1.0 m) faces across a 0.5 m
    gap: from 0.1 m off the wall the full 0.25 m clearance fits nowhere, the way out is along the gap."""
    t, h = 0.1, 2.6
    boxes = [Box((0, -t, 0), (6, 0, h)), Box((0, 4, 0), (6, 4 + t, h)),
             Box((-t, 0, 0), (0, 4, h)), Box((6, 0, 0), (6 + t, 4, h)),
             Box((0, 0.5, 0), (3.0, 1.0, 1.0))]
    return BoxWorld(boxes=boxes, floors=[Box((0, 0, -0.1), (6, 4, 0.0))], start=START)


def _pano(world: BoxWorld, pos, heading_rad: float):
    robot = BoxWorldRobot(world, PinholeCamera(64, 64, 90.0))
    robot.reset(Pose(position_m=pos, heading_rad=heading_rad))
    return robot.observe()


@pytest.mark.parametrize("heading_rad", [0.3, -2.0])
def test_a_robot_beside_a_wall_gets_away_from_it(heading_rad):
    world = _alcove()
    pano = _pano(world, START, heading_rad)
    escape_off = GeometricPredictorConfig(escape_clearance_m=GeometricPredictorConfig().clearance_m)
    assert GeometricPredictor(escape_off).predict_full(pano).candidates == []  # what every map's episode met

    p = GeometricPredictor()
    pr = p.predict_full(pano)
    assert pr.clearance_m == p.config.escape_clearance_m
    assert pr.candidates
    for c in pr.candidates:
        # Away from the wall or along it, never into it, and to a place the escape disc fits.
        assert c.dy_m > -1e-9, f"candidate {c} heads into the wall at y = 0"
        end = np.add(START[:2], (c.dx_m, c.dy_m))
        assert not world.blocked(end[0], end[1], 0.0, p.config.escape_clearance_m), f"candidate {c} ends in an obstacle"
        k = int(round((c.angle_rad % (2 * math.pi)) / (2 * math.pi / p.config.angle_bins))) % p.config.angle_bins
        assert c.distance_m <= pr.free_distance_m[k] + 1e-9


def test_an_exploration_dead_end_stays_one():
    """The exploration's predictor does not escape: its dead ends are left along the graph, and escape
    frontiers reordered the walk of both two-floor houses of the seed-0 set (discovery.WIDE_EXPLORATION)."""
    pano = _pano(_alcove(), START, 0.3)
    for profile in ("default", "cluttered-scan"):
        config = GeometricPredictorConfig(**discovery_config(profile).predictor_config)
        assert GeometricPredictor(config).predict_full(pano).candidates == [], profile


def test_a_panorama_with_room_to_move_keeps_its_candidates(world):
    """The escape sweep never runs where the full clearance leaves a candidate: same candidates, heatmap
    and free distances as with it switched off, to the bit."""
    p = GeometricPredictor()
    off = GeometricPredictor(GeometricPredictorConfig(escape_clearance_m=p.config.clearance_m))
    for pos in [(1.0, 1.0, 0.0), (0.4, 0.4, 0.0), (5.6, 3.6, 0.0), (3.5, 1.2, 0.0), (2.0, 3.8, 0.0)]:
        pano = _pano(world, pos, 0.3)
        a, b = p.predict_full(pano), off.predict_full(pano)
        assert a.candidates and a.candidates == b.candidates
        assert a.clearance_m == b.clearance_m == p.config.clearance_m
        np.testing.assert_array_equal(a.heatmap, b.heatmap)
        np.testing.assert_array_equal(a.free_distance_m, b.free_distance_m)


def test_escape_clearance_is_range_checked():
    with pytest.raises(ValueError):
        GeometricPredictorConfig(escape_clearance_m=-0.01)
    with pytest.raises(ValueError):
        GeometricPredictorConfig(escape_clearance_m=1.5)
