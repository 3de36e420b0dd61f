"""Frames ray-cast from a scene of boxes (open3d's RaycastingScene): what a test's tours record where the
simulator's generated houses would be more than it needs."""

from __future__ import annotations

import numpy as np

from shared.geometry import camera_pose
from shared.o3d import o3d
from shared.schemas import CameraIntrinsics


def box_scene(boxes) -> o3d.t.geometry.RaycastingScene:
    """A scene of axis-aligned boxes, each ``(lo, hi)`` corners (m)."""
    mesh = o3d.geometry.TriangleMesh()
    for lo, hi in boxes:
        mesh += o3d.geometry.TriangleMesh.create_box(*np.subtract(hi, lo)).translate(lo)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def cast_view(scene, camera: CameraIntrinsics, position_m, heading_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(float32 z-depth (H, W), 0 where a ray hits nothing; the hit points (H, W, 3), the camera's position
    where it hits nothing) of the robot's camera at ``position_m`` facing ``heading_rad``."""
    cam = camera.pinhole()
    world_from_cam = camera_pose(position_m, heading_rad)
    u, v = np.meshgrid(np.arange(cam.width_px), np.arange(cam.height_px))
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], axis=-1)
    d_world = rays.reshape(-1, 3) @ world_from_cam[:3, :3].T  # z-depth 1 along the optical axis
    origin = np.broadcast_to(world_from_cam[:3, 3], d_world.shape)
    t = scene.cast_rays(o3d.core.Tensor(np.c_[origin, d_world].astype(np.float32)))["t_hit"].numpy()
    t = np.where(np.isfinite(t), t, 0.0)
    hits = (origin + d_world * t[:, None]).reshape(cam.height_px, cam.width_px, 3)
    return t.reshape(cam.height_px, cam.width_px).astype(np.float32), hits
