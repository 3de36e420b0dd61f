"""Fixtures of the reconstructor tests: one small generated house, explored and toured for real."""

from __future__ import annotations

import logging

import numpy as np
from shared.o3d import o3d
import pytest

from shared.schemas import CameraIntrinsics

log = logging.getLogger(__name__)

# Small houses that the mapper explores and tours in a few seconds at 64 px; the first that
# completes is used (a failure of the mapper on one house is the mapper's test to catch).
HOUSES = ("generated:3:area=50", "generated:0:area=60", "generated:4:area=50")


class HouseRun:
    def __init__(self, robot, discovery, recordings):
        self.robot = robot
        self.discovery = discovery
        self.recordings = recordings
        self.label_names = dict(robot.scene.label_names)
        rc = o3d.t.geometry.RaycastingScene()
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(robot.scene.vertices.astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(robot.scene.triangles.astype(np.int32))
        rc.add_triangles(mesh)
        self._rc = rc

    def mesh_distance(self, xyz: np.ndarray) -> np.ndarray:
        """Exact distance of each point to the scene mesh."""
        return self._rc.compute_distance(o3d.core.Tensor(np.asarray(xyz, np.float32))).numpy()

    def free_path_m(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """How far a ray from each origin along its unit direction runs before it meets the mesh (inf: never)."""
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        return self._rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()


@pytest.fixture(scope="session")
def house() -> HouseRun:
    from services.mapper.core import MapperError, discover, execute_tours
    from services.robot_io.core.robot import ROBOTS

    cam = CameraIntrinsics(width_px=64, height_px=64, hfov_deg=90.0)
    errors = []
    for spec in HOUSES:
        try:
            robot = ROBOTS.create("sim", {"scene": spec, "camera": cam, "render_threads": 2})
            d = discover(robot)
            recs = execute_tours(robot, d.tours, d.scene, rate_hz=2.0)
        except (MapperError, IndexError) as exc:  # noqa: PERF203 - a handful of houses
            errors.append(f"{spec}: {type(exc).__name__}: {exc}")
            log.warning("house %s could not be toured: %s", spec, exc)
            continue
        if len(recs) >= 2 and all(r.frames for r in recs):
            return HouseRun(robot, d, recs)
        errors.append(f"{spec}: {len(recs)} recordings")
    pytest.fail("no test house could be explored and toured: " + "; ".join(errors))
