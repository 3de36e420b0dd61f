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


def test_a_frames_error_is_split_between_the_panoramas_and_the_drift_between_them():
    """bench.tour_drift's split of a tour frame's error: odometry drifts 4 cm in x between two
    panoramas, linearly in time; the graph placed the second panorama 2 cm short. Under the panoramas'
    true corrections the frames are exact (the drift between was linear); under the graph's they carry
    its 2 cm, growing along the way; as recorded, what the recording says."""
    from types import SimpleNamespace

    from bench.tour_drift import _between_panoramas
    from shared.schemas import Pose

    def pose(x: float) -> Pose:
        return Pose(position_m=(x, 0.0, 0.0), heading_rad=0.0)

    drift = lambda t: 0.04 * t / 10.0  # noqa: E731 - odometry's x error at time t
    pano_truth = {0.0: (pose(0.0), pose(0.0)), 10.0: (pose(2.0), pose(2.0 + drift(10.0)))}
    steps = [SimpleNamespace(timestamp_s=0.0), SimpleNamespace(timestamp_s=10.0)]
    # the graph's corrections (map = odom + dx): exact at the first, 2 cm short of -4 cm at the second
    loc = SimpleNamespace(steps=steps, schedule=lambda: (np.array([0.0, 10.0]),
                                                         np.array([[0.0, 0.0, 0.0], [-0.02, 0.0, 0.0]])))
    ts = [2.5, 5.0, 7.5]
    truth = {k: (pose(0.2 * t), pose(0.2 * t + drift(t))) for k, t in enumerate(ts)}
    frames = [SimpleNamespace(index=k, timestamp_s=t, pose=pose(0.2 * t + 0.01)) for k, t in enumerate(ts)]
    b = _between_panoramas([SimpleNamespace(frames=frames)], truth, pano_truth, loc)
    assert b.shape == (3, 6)
    assert np.allclose(b[:, 0], 0.01)  # as recorded
    assert np.allclose(b[:, 1], [0.005, 0.01, 0.015])  # the graph's 2 cm, interpolated
    assert np.allclose(b[:, 2], 0.0, atol=1e-12) and np.allclose(b[:, 4], 0.0, atol=1e-12)


def test_rooms_are_the_panoramas_the_fully_pinned_edges_join_and_a_room_off_as_a_block_says_so():
    """bench.tour_drift's rooms (issue 33): the pose graph's panoramas joined by fully pinned scan edges;
    a room placed against the others by odometry alone sits off as a block, its panoramas rigid
    within it, so its error is its block offset and little is left once that is taken off."""
    from bench.tour_drift import room_blocks, rooms

    room = rooms(7, [(0, 1), (1, 2), (4, 3), (5, 6), (6, 4)])
    assert room.tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert rooms(3, []).tolist() == [0, 1, 2]  # no edge: each panorama its own room
    rng = np.random.default_rng(5)
    true_xy = rng.uniform(-4, 4, (7, 2))
    own = rng.normal(0.0, 0.001, (7, 2))  # each panorama's own millimetre
    placed = true_xy + own
    placed[room == 1] += [0.02, -0.01]  # the second room 2.2 cm off as a block
    (k0, n0, off0, med0, rest0), (k1, n1, off1, med1, rest1) = room_blocks(room, placed, true_xy)
    assert (k0, n0, k1, n1) == (0, 3, 1, 4)
    assert np.allclose(off1, [0.02, -0.01] + own[room == 1].mean(axis=0))
    assert med1 > 0.015 and rest1 < 0.003
    assert np.hypot(*off0) < 0.003 and med0 < 0.004
