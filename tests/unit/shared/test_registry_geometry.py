import math

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial import cKDTree

from shared import geometry as g
from shared.registry import BackendConfig, Registry, UnknownBackendError


def test_registry_creates_by_name_with_typed_config():
    reg: Registry = Registry("thing")

    class Cfg(BackendConfig):
        radius_m: float = 0.1

    @reg.register("a", Cfg)
    class A:
        def __init__(self, cfg):
            self.cfg = cfg

    assert reg.create("a", {"radius_m": 0.3}).cfg.radius_m == 0.3
    assert reg.create("a").cfg.radius_m == 0.1
    with pytest.raises(ValidationError):
        reg.create("a", {"radius": 0.3})  # unknown fields are an error
    with pytest.raises(UnknownBackendError, match="known: a"):
        reg.create("b")
    with pytest.raises(ValueError):
        reg.register("a", Cfg)(A)


def test_camera_projects_forward_point_to_centre_and_left_point_left():
    cam = g.PinholeCamera(256, 256, 90.0)
    assert cam.fx == pytest.approx(128.0)
    pose = g.camera_pose((0, 0, 0), heading_rad=0.0)
    pts = g.world_to_camera(np.array([[2.0, 0, 1.25], [2.0, 1.0, 1.25], [2.0, 0, 2.25]]), pose)
    uv = pts[:, :2] / pts[:, 2:] * cam.fx + [cam.cx, cam.cy]
    assert uv[0] == pytest.approx([cam.cx, cam.cy])
    assert uv[1][0] < cam.cx  # +y is to the left when facing +x
    assert uv[2][1] < cam.cy  # up is towards the top of the image


def test_depth_back_projection_inverts_projection():
    cam = g.PinholeCamera(64, 48, 60.0)
    pose = g.camera_pose((1, 2, 0), 0.7, 0.2)
    depth = np.full((48, 64), 3.0, np.float32)
    pts, valid = g.depth_to_points(depth, cam, pose)
    back = g.world_to_camera(pts, pose)
    assert valid.all() and np.allclose(back[:, 2], 3.0)


def test_panorama_rotates_right():
    h = g.panorama_headings(0.0)
    assert h[1] == pytest.approx(-math.pi / 6) and len(h) == 12


@pytest.mark.parametrize("heading", [0.0, 1.0, -2.0, 3.0])
def test_habitat_conversion_round_trip(heading):
    q = g.heading_to_habitat_quaternion(heading)
    assert g.habitat_quaternion_to_heading(q) == pytest.approx(heading)
    p = np.array([[1.0, 2.0, 3.0]])
    assert np.allclose(g.world_to_habitat(g.habitat_to_world(p)), p)
    # Habitat's up (+y) is our +z.
    assert np.allclose(g.habitat_to_world([0, 1, 0]), [0, 0, 1])


def test_camera_poses_are_the_stacked_camera_pose_bit_for_bit():
    from shared.geometry import camera_pose, camera_poses

    rng = np.random.default_rng(11)
    for _ in range(20):
        pos = rng.uniform(-30, 30, 3)
        heads = rng.uniform(-4, 4, 12)
        pitch = rng.choice([0.0, float(rng.uniform(-1, 1))])
        ref = np.stack([camera_pose(pos, h, pitch, 1.25) for h in heads])
        assert camera_poses(pos, heads, pitch, 1.25).tobytes() == ref.tobytes()
    pitches = rng.uniform(-1, 1, 5)
    ref = np.stack([camera_pose(pos, 0.3, p, 0.9) for p in pitches])
    assert camera_poses(pos, np.full(5, 0.3), pitches, 0.9).tobytes() == ref.tobytes()


def test_planar_between_gives_the_transform_planar_apply_undoes_drift_with():
    from shared.geometry import planar_apply, planar_between

    odo, true = ((1.0, 0.0, 0.2), 0.3), ((2.0, 4.0, 0.2), 0.3 + math.pi / 2)
    t, yaw = planar_between(*odo, *true)
    assert abs(yaw - math.pi / 2) < 1e-12
    xyz, heading = planar_apply(t, yaw, *odo)
    assert np.allclose(xyz, true[0], atol=1e-12) and abs(heading - true[1]) < 1e-12
    # A quarter turn about +z then a shift: (1, 0) -> (0, 1) -> (2, 4).
    xyz, heading = planar_apply((2.0, 3.0, 0.0), math.pi / 2, (1.0, 0.0, 0.0), 3.0)
    assert np.allclose(xyz, (2.0, 4.0, 0.0), atol=1e-12) and abs(heading - (3.0 + math.pi / 2 - 2 * math.pi)) < 1e-12


def test_normals_agree_with_eigh_to_rounding():
    # The closed-form smallest eigenvector (the reconstructor's registration and the renderer's normals) against
    # LAPACK's: a noisy tilted plane, a round patch (the two largest eigenvalues equal, where the cubic's root
    # loses digits), a line and repeated points (no normal: eigh decides, as it did).
    rng = np.random.default_rng(3)
    turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    grid = np.stack(np.meshgrid(np.arange(20) * 0.05, np.arange(20) * 0.05), -1).reshape(-1, 2)
    ring = np.arange(12) * math.pi / 6
    clouds = [np.c_[grid, rng.normal(0.0, 0.004, len(grid))] @ turn.T + 1.5,
              np.c_[np.cos(ring), np.sin(ring), np.zeros(12)] * 0.05 @ turn.T,
              np.c_[np.linspace(0.0, 1.0, 30), np.zeros(30), np.zeros(30)],
              np.ones((12, 3))]
    for xyz in clouds:
        _, idx = cKDTree(xyz).query(xyz, k=12)
        nb = xyz[idx] - xyz[idx].mean(axis=1, keepdims=True)
        want = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))[1][:, :, 0]
        got = g.pca_normals(xyz[idx])
        sign = np.where(np.einsum("ij,ij->i", got, want) < 0.0, -1.0, 1.0)
        assert np.abs(got * sign[:, None] - want).max() < 1e-12
