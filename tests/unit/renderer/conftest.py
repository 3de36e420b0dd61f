"""Fixtures of the renderer tests: a built two-room flat, its sampled cloud and index."""

from __future__ import annotations

import numpy as np
import pytest

from services.renderer.tools import scenes
from shared.cloud import PointCloud, quantise_view_dirs
from libs.pointrender import IndexedCloud


@pytest.fixture(scope="session")
def room_mesh() -> scenes.LabelledMesh:
    return scenes.built_room()


@pytest.fixture(scope="session")
def room_cloud(room_mesh):
    return scenes.sample_mesh(room_mesh, 1_000_000, seed=1)


@pytest.fixture(scope="session")
def room_index(room_cloud) -> IndexedCloud:
    return IndexedCloud(room_cloud)


@pytest.fixture(scope="session")
def room_index_sided(room_mesh) -> IndexedCloud:
    """The flat as if every point had been seen from one spot in it (its view_dirs point there):
    faces turned away from that spot are seen from behind by some views, so the side test of the
    visibility mode has work in both rooms. 250k points, not room_cloud's 1e6: its tests compare two
    paths' images of it (compiled and array code, numpy and torch), which a sparser flat holds as
    well, and its side vote (a neighbour query per point) and voxel levels are its own, not shared
    with room_index: 3.7 s of CPU at 1e6 points, 1.1 s here with the spacing and normals too."""
    c = scenes.sample_mesh(room_mesh, 250_000, seed=1)
    to_spot = np.array([2.0, 1.0, 1.25]) - c.xyz
    unit = to_spot / np.linalg.norm(to_spot, axis=1, keepdims=True)
    return IndexedCloud(PointCloud(c.xyz, c.rgb, c.labels, c.label_names, quantise_view_dirs(unit)))


@pytest.fixture(scope="session")
def room_gt(room_mesh) -> scenes.RaycastCamera:
    return scenes.RaycastCamera(room_mesh)
