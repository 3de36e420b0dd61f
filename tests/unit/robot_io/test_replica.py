"""The real scanned Replica office: load, render at the recorded poses, compare with recorded depth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from libs.world.navgrid import NavGrid
from services.robot_io.core.render import Intrinsics, SceneRenderer
from libs.world.scene import load_scene


@pytest.fixture(scope="module")
def office(shared_data):
    root = shared_data / "replica_office0"
    scene = load_scene(str(root / "office0_mesh.ply"))
    return root, scene, SceneRenderer(scene)


def test_depth_matches_recorded_frames(office):
    root, scene, renderer = office
    cam = json.loads((root / "cam_params.json").read_text())["camera"]
    k = Intrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"], cam["w"], cam["h"])
    poses = np.loadtxt(root / "traj.txt", max_rows=4).reshape(-1, 4, 4)
    out = renderer.render(poses, k)
    for i in range(4):
        recorded = cv2.imread(str(root / "frames" / f"depth{i:06d}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / cam["scale"]
        valid = (recorded > 0) & (out.depth_m[i] > 0)
        assert valid.mean() > 0.95
        err = np.abs(out.depth_m[i][valid] - recorded[valid])
        assert np.median(err) < 0.01, f"frame {i}: median depth error {np.median(err):.4f} m"
        # A wrong pose convention would still give some matches; most pixels must agree.
        assert np.mean(err < 0.05) > 0.95
    assert out.semantic is not None and np.all(out.semantic == -1)  # scans carry no labels


def test_office_is_walkable(office):
    _, scene, renderer = office
    nav = NavGrid(scene, raycasting_scene=renderer.raycasting_scene)
    assert nav.reachable_area_m2 > 3.0
    rng = np.random.default_rng(0)
    a, b = nav.sample_navigable(rng, 2)
    assert np.isfinite(nav.geodesic_distance(a, b))
