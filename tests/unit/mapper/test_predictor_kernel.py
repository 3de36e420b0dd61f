"""The compiled column walk of the geometric predictor gives exactly the array version's hits.

Real panoramas from robot-io's simulator: a two-floor house observed at random walkable spots, the
stairwell's nodes included (the tentative-climb and confirmed-flight paths), with and without depth
noise and holes, at two image sizes and pixel strides; and the Replica office where the data is here.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.mapper.core.predictor import (GeometricPredictor, GeometricPredictorConfig, _column_median_kernel,
                                            _column_median_within_noise, _profiles_kernel)
from services.robot_io.core.robot import ROBOTS
from shared.jit import AVAILABLE
from shared.schemas import CameraIntrinsics, Pose
from tests.conftest import SHARED_DATA

pytestmark = pytest.mark.skipif(not AVAILABLE, reason="numba is not installed: only the array version runs")

REPLICA = SHARED_DATA / "replica_office0" / "office0_mesh.ply"


def _panoramas(robot, n: int, seed: int, stairs_first: int = 0):
    rng = np.random.default_rng(seed)
    nav = robot.nav
    main = np.flatnonzero(nav.component == nav.main_component)
    nodes = nav.nodes_m[rng.choice(main, n)]
    if stairs_first:
        # Nodes between two storeys: on the flight itself.
        z = nav.nodes_m[main, 2]
        mid = main[(z > 0.3) & (z < z.max() - 0.3)]
        nodes[:stairs_first] = nav.nodes_m[rng.choice(mid, stairs_first)]
    out = []
    for p in nodes:
        robot.reset(Pose(position_m=tuple(p), heading_rad=float(rng.uniform(-np.pi, np.pi))))
        out.append(robot.observe())
    return out


def _compare(pano, predictor: GeometricPredictor) -> tuple[int, int]:
    c = predictor.config
    s = c.pixel_stride
    depth = np.asarray(pano.depth_m)[:, ::s, ::s]
    xn, yn, _ = predictor._columns(pano.camera.width_px, pano.camera.height_px, pano.camera.hfov_deg, s)
    results, profiles = [], []
    for use_kernel in (True, False):
        predictor.use_kernel = use_kernel
        predictor._memo.last = None
        profiles.append(predictor._profiles(depth, xn, yn))
        hits = predictor._walk_columns(pano)
        pred = predictor.predict_full(pano)
        results.append((hits, pred))
    predictor.use_kernel = True
    for a, b in zip(*profiles):  # the per-column height profile and its vertical faces
        assert a.tobytes() == b.tobytes()
    (h1, p1), (h0, p0) = results
    for name in ("hit", "doubt", "climbed", "azimuth_rad"):
        assert getattr(h1, name).tobytes() == getattr(h0, name).tobytes(), name
    assert p1.heatmap.tobytes() == p0.heatmap.tobytes()
    assert [c.model_dump() for c in p1.candidates] == [c.model_dump() for c in p0.candidates]
    return int(np.isfinite(h1.doubt).sum()), int(h1.climbed.sum())


def test_kernel_matches_array_walk_on_a_two_floor_house():
    cam = CameraIntrinsics(width_px=64, height_px=64, hfov_deg=90.0)
    robot = ROBOTS.create("sim", {"scene": "generated:1:floors=2:area=160", "camera": cam,
                                  "noise": {"depth_noise_rel": 0.01, "depth_hole_fraction": 0.05, "seed": 3}})
    noisy = _panoramas(robot, 6, seed=1, stairs_first=3)
    robot.noise.config = robot.noise.config.model_copy(update={"depth_noise_rel": 0.0, "depth_hole_fraction": 0.0})
    clean = _panoramas(robot, 16, seed=2, stairs_first=8)
    doubts = flights = 0
    for cfg in (GeometricPredictorConfig(), GeometricPredictorConfig(pixel_stride=1, angle_bins=360)):
        pred = GeometricPredictor(cfg)
        for pano in noisy + clean:
            d, f = _compare(pano, pred)
            doubts += d
            flights += f
    # The rarer branches ran: unconfirmed climbs and confirmed flights.
    assert doubts > 0 and flights > 0
    # Both strides' depth (a strided view, a contiguous array), the panoramas' read-only depth and the
    # writable smoothed copies ran one machine code per kernel, not one per layout (shared.jit.one_signature).
    assert len(_profiles_kernel.signatures) == 1, _profiles_kernel.signatures
    assert len(_column_median_kernel.signatures) == 1, _column_median_kernel.signatures


def test_noise_median_kernel_matches_the_array_version():
    # The noisy robot declares its depth noise, so the walks above ran on the smoothed depth; here the
    # smoothed depth itself, at several window sizes, holes included.
    robot = ROBOTS.create("sim", {"scene": "generated:1:floors=2:area=160",
                                  "camera": CameraIntrinsics(width_px=64, height_px=64, hfov_deg=90.0),
                                  "noise": {"depth_noise_rel": 0.01, "depth_hole_fraction": 0.05, "seed": 3}})
    changed = 0
    for pano in _panoramas(robot, 3, seed=5, stairs_first=1):
        depth = np.asarray(pano.depth_m)[:, ::2, ::2]
        for rows in (3, 5, 9):
            array = _column_median_within_noise(depth, pano.depth_noise_rel, rows, 4.0)
            compiled = np.empty(depth.shape, dtype=depth.dtype)
            _column_median_kernel(depth, rows, 4.0 * pano.depth_noise_rel, compiled)
            assert array.tobytes() == compiled.tobytes(), rows
            assert np.array_equal(array > 0, depth > 0)  # holes stay holes, measurements stay
            changed += int((array != depth).sum())
    assert changed > 0


@pytest.mark.skipif(not REPLICA.is_file(), reason="Replica office0 is not in the shared data")
def test_kernel_matches_array_walk_in_a_real_scan():
    cam = CameraIntrinsics(width_px=96, height_px=96, hfov_deg=90.0)
    robot = ROBOTS.create("sim", {"scene": str(REPLICA), "camera": cam})
    pred = GeometricPredictor()
    for pano in _panoramas(robot, 6, seed=4):
        _compare(pano, pred)
