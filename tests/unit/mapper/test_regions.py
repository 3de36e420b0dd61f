import numpy as np

from services.mapper.core.regions import detect_floors, detect_stair_positions


def test_detect_floors_ignores_stair_heights():
    z = np.concatenate([np.zeros(20), np.full(15, 2.8), [0.5, 0.9, 1.4, 1.9, 2.3]])
    assert detect_floors(z, 0.3, 3) == [0.0, 2.8]


def test_stairs_from_consecutive_vertical_moves():
    flat = np.column_stack([np.linspace(0, 3, 4), np.zeros(4), np.zeros(4)])
    stairs = np.column_stack([3 + np.arange(1, 6) * 0.6, np.zeros(5), np.arange(1, 6) * 0.5])
    top = np.column_stack([np.linspace(6.5, 8, 3), np.zeros(3), np.full(3, 2.5)])
    traj = np.concatenate([flat, stairs, top])
    pts = detect_stair_positions(traj, 0.1, 0.5)
    assert len(pts) == 6  # the run's start and its 5 rising poses
    assert pts[:, 2].min() == 0.0 and pts[:, 2].max() == 2.5
    # A single small bump is not a staircase.
    bump = traj.copy()
    bump[:, 2] = 0.0
    bump[5, 2] = 0.2
    assert len(detect_stair_positions(bump, 0.1, 0.5)) == 0
