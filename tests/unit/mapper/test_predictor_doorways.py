"""Doorway waypoints: an agent beside a wall gets an approach point lined up with the door."""

import math

import numpy as np

from shared.geometry import PinholeCamera
from shared.schemas import Pose

from services.mapper.core import GeometricPredictor, GeometricPredictorConfig
from services.mapper.tools.boxworld import BoxWorldRobot

DOOR_X = (1.5, 2.5)  # rooms_world: the wall y = 4 (0.1 m thick) has a door at x in [1.5, 2.5]
WALL_Y = 4.0


def _pano(world, pos, heading=0.0, size=96):
    r = BoxWorldRobot(world, PinholeCamera(size, size, 90.0))
    r.reset(Pose(position_m=pos, heading_rad=heading))
    return r.observe()


def _targets(pos, cands):
    return np.array([[pos[0] + c.dx_m, pos[1] + c.dy_m] for c in cands])


def test_doorway_beside_a_wall_gets_an_aligned_approach(world):
    pos = (3.3, 3.6, 0.0)  # 0.35 m from the wall face, right of the door: no straight way through
    pred = GeometricPredictor()
    full = pred.predict_full(_pano(world, pos, heading=0.3))
    c, s = math.cos(0.3), math.sin(0.3)

    def to_world(p):
        return np.array(pos[:2]) + np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]])

    # Both doors of the big room are found (the one in the wall x = 6 too), each with an approach.
    centres = [to_world(np.add(d.left_m, d.right_m) / 2) for d in full.doorways]
    ours = [d for d, w in zip(full.doorways, centres) if np.allclose(w, (2.0, WALL_Y - 0.05), atol=0.2)]
    assert len(ours) == 1, centres
    d = ours[0]
    assert 0.8 <= d.width_m <= 1.1 and not d.direct and d.approach_m is not None
    assert any(np.allclose(w, (6.0 - 0.05, 2.0), atol=0.2) for w in centres), centres
    # A candidate stands before the door, lined up with it, and the straight shot through clears the jambs.
    t = _targets(pos, full.candidates)
    before = (np.abs(t[:, 0] - 2.0) < 0.3) & (t[:, 1] < WALL_Y - 0.3) & (t[:, 1] > WALL_Y - 1.2)
    assert before.any(), t
    assert len(full.candidates) <= 5
    # No candidate runs the body into the wall beside the door.
    for tx, ty in t:
        assert ty < WALL_Y - 0.2 or DOOR_X[0] + 0.2 < tx < DOOR_X[1] - 0.2


def test_door_in_line_needs_no_approach(world):
    pos = (2.0, 2.8, 0.0)  # straight in front of the door
    full = GeometricPredictor().predict_full(_pano(world, pos, heading=math.pi / 2))
    through = [d for d in full.doorways if d.direct]
    assert through and all(d.approach_m is None for d in through)
    t = _targets(pos, full.candidates)
    assert np.any((t[:, 1] > WALL_Y + 0.3) & (np.abs(t[:, 0] - 2.0) < 0.4)), t


def test_doorways_can_be_switched_off(world):
    pos = (3.3, 3.6, 0.0)
    pano = _pano(world, pos, heading=0.3)
    off = GeometricPredictor(GeometricPredictorConfig(doorways=False)).predict_full(pano)
    assert off.doorways == []
    t = _targets(pos, off.candidates)
    assert not np.any((np.abs(t[:, 0] - 2.0) < 0.3) & (t[:, 1] < WALL_Y - 0.3) & (t[:, 1] > WALL_Y - 1.2))
