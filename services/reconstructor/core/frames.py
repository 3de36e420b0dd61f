"""Posed images: the one input type of the reconstruction backends.

A recorded tour arrives as ``shared.schemas.Frame`` messages (agent floor pose + camera pitch); a
dataset such as Replica gives full camera matrices. Both become :class:`PosedImage` (an OpenCV
``world_from_camera``), validated once here so the backends can trust their inputs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from shared.geometry import DEFAULT_CAMERA_HEIGHT_M, PinholeCamera, camera_pose, rot_z
from shared.schemas import Frame, Pose

from .errors import EmptyRecordingError, InvalidFrameError


@dataclass
class PosedImage:
    """One RGB(-D)(-semantic) image with its camera pose in the world (OpenCV camera axes)."""

    rgb: np.ndarray  # uint8 (H, W, 3)
    world_from_camera: np.ndarray  # float64 (4, 4)
    camera: PinholeCamera
    depth_m: np.ndarray | None = None  # float32 (H, W) z-depth, 0 = no measurement
    semantic: np.ndarray | None = None  # int32 (H, W), -1 = unknown
    index: int = 0
    timestamp_s: float = 0.0
    heading_rad: float = 0.0  # agent heading (odometry) when the image was taken
    imu_heading_rad: float = 0.0
    pitch_rad: float = 0.0
    depth_noise_rel: float = 0.0  # the sensor's depth sigma / depth^2 (``Frame.depth_noise_rel``)

    @property
    def position_m(self) -> np.ndarray:
        """Camera centre in the world."""
        return self.world_from_camera[:3, 3]


@dataclass
class RegionInput:
    """The recording of one region: its start pose (the local origin) and its images in order."""

    region: int
    start_pose: Pose
    images: list[PosedImage]
    camera_height_m: float = DEFAULT_CAMERA_HEIGHT_M
    meta: dict[str, Any] = field(default_factory=dict)

    def local_from_world(self) -> np.ndarray:
        """4x4 transform into the frame of the start pose (floor point, heading), z up."""
        t = np.eye(4)
        r = rot_z(-self.start_pose.heading_rad)
        t[:3, :3] = r
        t[:3, 3] = -r @ self.start_pose.xyz
        return t


class RecordingLike(Protocol):
    """What a region recording must offer (``services.mapper.core.RegionRecording`` does)."""

    region: int
    start_pose: Pose
    frames: list[Frame]


def posed_from_frame(frame: Frame, camera_height_m: float = DEFAULT_CAMERA_HEIGHT_M) -> PosedImage:
    """Validate a recorded ``Frame`` and give its camera pose (camera ``camera_height_m`` above the floor)."""
    pos = np.asarray(frame.pose.position_m, dtype=np.float64)
    scalars = (frame.pose.heading_rad, frame.pitch_rad, frame.imu_heading_rad)
    # Frames built with model_construct (or by a buggy producer) skip pydantic's finiteness checks.
    if pos.shape != (3,) or not np.isfinite(pos).all() or not all(math.isfinite(v) for v in scalars):
        raise InvalidFrameError(f"frame {frame.index}: non-finite pose {frame.pose.position_m}, {scalars}")
    cam = frame.camera.pinhole()
    hw = (cam.height_px, cam.width_px)
    rgb = np.asarray(frame.rgb)
    if rgb.shape != (*hw, 3) or rgb.dtype != np.uint8:
        raise InvalidFrameError(f"frame {frame.index}: rgb {rgb.shape} {rgb.dtype} does not match camera {hw}")
    depth = None if frame.depth_m is None else np.asarray(frame.depth_m, dtype=np.float32)
    if depth is not None and depth.shape != hw:
        raise InvalidFrameError(f"frame {frame.index}: depth {depth.shape} does not match camera {hw}")
    sem = None if frame.semantic is None else np.asarray(frame.semantic, dtype=np.int32)
    if sem is not None and sem.shape != hw:
        raise InvalidFrameError(f"frame {frame.index}: semantic {sem.shape} does not match camera {hw}")
    return PosedImage(
        rgb=rgb,
        world_from_camera=camera_pose(pos, frame.pose.heading_rad, frame.pitch_rad, camera_height_m),
        camera=cam,
        depth_m=depth,
        semantic=sem,
        index=frame.index,
        timestamp_s=frame.timestamp_s,
        heading_rad=float(frame.pose.heading_rad),
        imu_heading_rad=float(frame.imu_heading_rad),
        pitch_rad=float(frame.pitch_rad),
        depth_noise_rel=float(frame.depth_noise_rel),
    )


def region_from_frames(
    region: int,
    start_pose: Pose,
    frames: Sequence[Frame],
    camera_height_m: float = DEFAULT_CAMERA_HEIGHT_M,
) -> RegionInput:
    """A :class:`RegionInput` from recorded frames; raises on an empty or malformed recording."""
    if not frames:
        raise EmptyRecordingError(f"region {region}: no frames")
    sp = np.asarray(start_pose.position_m, dtype=np.float64)
    if not np.isfinite(sp).all() or not math.isfinite(start_pose.heading_rad):
        raise InvalidFrameError(f"region {region}: non-finite start pose")
    images = [posed_from_frame(f, camera_height_m) for f in frames]
    return RegionInput(region, start_pose, images, camera_height_m)


def region_from_recording(rec: RecordingLike, camera_height_m: float = DEFAULT_CAMERA_HEIGHT_M) -> RegionInput:
    """Adapter for the mapper's ``RegionRecording`` (or anything with region, start_pose, frames)."""
    return region_from_frames(rec.region, rec.start_pose, rec.frames, camera_height_m)


def posed_from_matrix(
    rgb: np.ndarray,
    world_from_camera: np.ndarray,
    camera: PinholeCamera,
    depth_m: np.ndarray | None = None,
    index: int = 0,
    timestamp_s: float = 0.0,
) -> PosedImage:
    """A posed image from a full camera matrix (datasets); heading and pitch are read off its axes."""
    t = np.asarray(world_from_camera, dtype=np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise InvalidFrameError(f"image {index}: world_from_camera must be a finite 4x4 matrix")
    fwd = t[:3, 2]
    heading = math.atan2(fwd[1], fwd[0])
    pitch = math.asin(max(-1.0, min(1.0, fwd[2])))
    return PosedImage(rgb=np.asarray(rgb, np.uint8), world_from_camera=t, camera=camera,
                      depth_m=None if depth_m is None else np.asarray(depth_m, np.float32),
                      index=index, timestamp_s=timestamp_s, heading_rad=heading,
                      imu_heading_rad=heading, pitch_rad=pitch)
