"""The invariant of shared/geometry.py: a scene file's conversion equals habitat_to_world after
Habitat's own transform of the file, so R2R-CE positions land where Habitat puts them."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry import _HAB_TO_WORLD, habitat_alignment, habitat_to_world, scene_file_to_world, world_to_habitat


def test_habitat_frame_file_converts_exactly_like_habitat_positions():
    assert np.array_equal(scene_file_to_world(), _HAB_TO_WORLD)
    p = np.random.default_rng(0).normal(size=(50, 3))
    assert np.allclose(p @ scene_file_to_world().T, habitat_to_world(p))


def test_z_up_front_y_files_are_the_world_unchanged():
    # Matterport3D (and Replica) as Habitat loads them: up +z, front +y.
    assert np.allclose(scene_file_to_world((0, 0, 1), (0, 1, 0)), np.eye(3))


@pytest.mark.parametrize("seed", range(5))
def test_any_frame_is_habitat_to_world_after_habitats_alignment(seed):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    up, front = q[:, 0], q[:, 1]
    scale = rng.uniform(0.1, 3.0, 3)
    r = habitat_alignment(up, front)
    # Habitat's alignment sends the file's up to +y and its front to -z, and is a rotation.
    assert np.allclose(r @ up, [0, 1, 0]) and np.allclose(r @ front, [0, 0, -1])
    assert np.linalg.det(r) == pytest.approx(1.0)
    m = scene_file_to_world(up, front, scale)
    p = rng.normal(size=(20, 3))
    hab = (p * scale) @ r.T  # where Habitat puts the vertices
    assert np.allclose(p @ m.T, habitat_to_world(hab))
    assert np.allclose(world_to_habitat(p @ m.T), hab)


def test_bad_frames_are_rejected():
    with pytest.raises(ValueError):
        habitat_alignment((0, 1, 0), (0, 2, 0))
    with pytest.raises(ValueError):
        habitat_alignment((0, 0, 0), (0, 0, -1))
    with pytest.raises(ValueError):
        scene_file_to_world(scale=(1, -1, 1))  # a mirror would turn every face inside out
