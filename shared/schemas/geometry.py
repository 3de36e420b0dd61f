"""Poses, camera intrinsics and view poses."""

from __future__ import annotations


import numpy as np
from pydantic import Field

from shared.geometry import PinholeCamera

from .base import Message, Pitch_rad, Radians, Xyz_m


# --- geometry ------------------------------------------------------------------------------------


class Pose(Message):
    """Agent pose: floor point under the agent (metres, world z-up) and heading."""

    position_m: Xyz_m
    heading_rad: Radians = 0.0

    @property
    def xyz(self) -> np.ndarray:
        return np.asarray(self.position_m, dtype=np.float64)


class CameraIntrinsics(Message):
    width_px: int = Field(256, ge=8, le=4096)
    height_px: int = Field(256, ge=8, le=4096)
    hfov_deg: float = Field(90.0, ge=1.0, le=179.0)

    def pinhole(self) -> PinholeCamera:
        return PinholeCamera(self.width_px, self.height_px, self.hfov_deg)


class ViewPose(Message):
    """A camera to render from: agent floor position, heading and pitch."""

    position_m: Xyz_m
    heading_rad: Radians = 0.0
    pitch_rad: Pitch_rad = 0.0
