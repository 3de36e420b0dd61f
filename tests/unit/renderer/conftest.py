"""Fixtures of the renderer tests: a built two-room flat, its sampled cloud and index."""

from __future__ import annotations

import numpy as np
import pytest

from services.renderer.tools import scenes
from shared.cloud import PointCloud, quantise_view_dirs
from libs.pointrender import IndexedCloud, SplatConfig
from libs.pointrender.splat import point_normals_of, share_point_geometry


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
def room_index_sided(room_cloud, room_index) -> IndexedCloud:
    """The flat's cloud as if every point had been seen from one spot in it (its view_dirs point
    there): faces turned away from that spot are seen from behind by some views, so the side test
    of the visibility mode has work in both rooms."""
    to_spot = np.array([2.0, 1.0, 1.25]) - room_cloud.xyz
    unit = to_spot / np.linalg.norm(to_spot, axis=1, keepdims=True)
    c = room_cloud
    sided = IndexedCloud(PointCloud(c.xyz, c.rgb, c.labels, c.label_names, quantise_view_dirs(unit)))
    # The same points in the same order as room_index (same cloud, block size and shuffle seed), so the
    # same k-d tree, spacing and normals: computed once for both (a 1e6-point neighbour query and eigen-solve,
    # 3.9 s of CPU), not once per index. The sides (normals turned by view_dirs) are still its own.
    cfg = SplatConfig()
    point_normals_of(room_index, cfg.normal_neighbours, cfg.spacing_neighbours)
    assert share_point_geometry(room_index, sided) == 3  # the k-d tree, the spacing and the normals
    return sided


@pytest.fixture(scope="session")
def room_gt(room_mesh) -> scenes.RaycastCamera:
    return scenes.RaycastCamera(room_mesh)
