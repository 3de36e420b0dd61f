"""Fixtures of the renderer tests: a built two-room flat, its sampled cloud and index."""

from __future__ import annotations

import pytest

from services.renderer.tools import scenes
from shared.pointrender import IndexedCloud


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
def room_gt(room_mesh) -> scenes.RaycastCamera:
    return scenes.RaycastCamera(room_mesh)
