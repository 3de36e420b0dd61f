"""bench.tour_drift's split by floor (issue 33, the two-floor house): the floors are found among the
panoramas' true heights, and a floor's error is split into one rigid offset and what is left."""

import math

import numpy as np

from bench.tour_drift import levels, rigid_fit


def test_levels_are_the_heights_most_panoramas_stand_at_not_the_stairs_between():
    # Two floors 2.8 m apart and a climb with a panorama on every step (0.19 m): a gap-based
    # clustering sees one level; the floors are where the panoramas crowd.
    z = np.concatenate([np.zeros(40), np.full(35, 2.8), np.arange(1, 15) * 0.187])
    assert np.allclose(levels(z), [0.0, 2.8])
    assert len(levels(np.zeros(10))) == 1
    assert len(levels(np.zeros(0))) == 0


def test_rigid_fit_recovers_a_floor_offset_and_leaves_each_panorama_its_own_error():
    rng = np.random.default_rng(3)
    truth = rng.uniform(-5, 5, (30, 2))
    yaw = math.radians(0.4)
    r = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    placed = (truth - np.array([0.05, -0.03])) @ r  # the floor off by 5.8 cm and 0.4 deg, rigidly
    t, fit_yaw, res = rigid_fit(placed, truth)
    assert abs(math.degrees(fit_yaw) - 0.4) < 1e-6
    assert res.max() < 1e-9
    own = placed.copy()
    own[0] += [0.04, 0.0]  # one panorama off its floor by 4 cm: the residual says which
    _, _, res = rigid_fit(own, truth)
    assert res.argmax() == 0 and res[0] > 0.03
