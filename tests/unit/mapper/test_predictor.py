import math

import numpy as np
import pytest

from shared.geometry import PinholeCamera
from shared.schemas import CandidateKind, Pose

from services.mapper.core import PREDICTORS, GeometricPredictor, GeometricPredictorConfig
from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world


def _pano(world, pos, heading=0.0, size=64):
    r = BoxWorldRobot(world, PinholeCamera(size, size, 90.0))
    r.reset(Pose(position_m=pos, heading_rad=heading))
    return r.observe()


def test_registry_default_and_contract(world):
    pred = PREDICTORS.create("geometric")
    cands = pred.predict(_pano(world, (1.0, 1.0, 0.0)))
    assert 1 <= len(cands) <= 5
    assert [c.index for c in cands] == list(range(len(cands)))
    assert all(c.kind == CandidateKind.WAYPOINT for c in cands)
    assert all(0.25 <= c.distance_m <= 3.0 for c in cands)
    scores = [c.score for c in cands]
    assert scores == sorted(scores, reverse=True)


@pytest.mark.parametrize("heading", [0.0, 1.0, -2.5])
def test_world_offsets_agree_with_relative_angle(world, heading):
    pano = _pano(world, (2.0, 3.0, 0.0), heading)
    for c in GeometricPredictor().predict(pano):
        assert math.isclose(c.dx_m, c.distance_m * math.cos(heading + c.angle_rad), abs_tol=1e-9)
        assert math.isclose(c.dy_m, c.distance_m * math.sin(heading + c.angle_rad), abs_tol=1e-9)


def test_free_distance_matches_walls(world):
    # At (1, 1) facing +x: the wall x=0 is 1 m behind, the wall y=0 1 m to the right, and the
    # divider x=6 about 5 m ahead (the door is at y 1.5-2.5).
    p = GeometricPredictor()
    pr = p.predict_full(_pano(world, (1.0, 1.0, 0.0), 0.0))
    clearance = p.config.clearance_m
    def free_at(deg):
        return pr.free_distance_m[int(round((deg % 360) / 3.0)) % 120]
    assert free_at(180) == pytest.approx(1.0 - clearance, abs=0.12)
    assert free_at(-90) == pytest.approx(1.0 - clearance, abs=0.12)
    assert free_at(0) > 4.0


def test_heading_rotates_the_profile(world):
    p = GeometricPredictor()
    a = p.predict_full(_pano(world, (2.0, 3.0, 0.0), 0.0)).free_distance_m
    b = p.predict_full(_pano(world, (2.0, 3.0, 0.0), math.pi / 2)).free_distance_m
    # Turning left by 90 deg shifts relative angles by -30 bins.
    assert np.median(np.abs(np.roll(a, -30) - b)) < 0.1


def test_candidates_never_into_close_obstacles(world):
    p = GeometricPredictor()
    for pos in [(0.4, 0.4, 0.0), (5.6, 3.6, 0.0), (3.5, 1.2, 0.0), (2.0, 3.8, 0.0)]:
        pano = _pano(world, pos, 0.3)
        pr = p.predict_full(pano)
        for c in pr.candidates:
            k = int(round((c.angle_rad % (2 * math.pi)) / (2 * math.pi / 120))) % 120
            assert c.distance_m <= pr.free_distance_m[k] + 1e-9
            end = np.array(pos[:2]) + [c.dx_m, c.dy_m]
            assert not world.blocked(end[0], end[1], 0.0, p.config.body_radius_m)


def test_table_is_an_obstacle_and_stairs_are_not():
    world = rooms_world(with_stairs=True)
    p = GeometricPredictor()
    # Facing the table top (0.7-0.76 m high) from 1.5 m: blocked before it.
    pr = p.predict_full(_pano(world, (1.5, 1.9, 0.0), 0.0))
    assert pr.free_distance_m[0] < 1.5
    # At the foot of the staircase facing up it (+x): walkable for the whole range.
    pr = p.predict_full(_pano(world, (3.5, 7.15, 0.0), 0.0))
    assert pr.free_distance_m[0] >= 3.0
    assert any(abs(c.angle_rad) < math.radians(10) for c in pr.candidates)


def test_unseen_directions_are_closed(world):
    pano = _pano(world, (2.0, 3.0, 0.0))
    pano.depth_m[:] = 0.0  # nothing measured: treated as open space within sensor range
    p = GeometricPredictor()
    assert np.all(p.free_distance(pano) == p.config.sensor_range_m)
    narrow = pano.model_copy(update={"headings_rad": pano.headings_rad[:1],
                                     "depth_m": pano.depth_m[:1], "rgb": pano.rgb[:1]})
    free = p.free_distance(narrow)
    assert (free == 0).sum() > 60  # a single 90 deg view leaves most directions unknown


def test_config_validation():
    with pytest.raises(ValueError):
        GeometricPredictorConfig(min_distance_m=3.0, max_distance_m=1.0)
    with pytest.raises(ValueError):
        PREDICTORS.create("geometric", {"nope": 1})
