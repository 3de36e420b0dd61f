"""Sensor realism: depth noise and holes, odometry and IMU drift. Everything is off by default and seeded."""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from shared.geometry import wrap_angle
from shared.registry import BackendConfig
from shared.schemas import DepthNoiseRel, Pose


class SensorNoiseConfig(BackendConfig):
    """Noise model parameters (all zero = a perfect sensor)."""

    seed: int = 0
    depth_noise_rel: DepthNoiseRel = 0.0  # sigma = rel * z^2 (structured-light-like)
    depth_hole_fraction: float = Field(0.0, ge=0.0, le=0.9)  # pixels dropped at random
    depth_max_m: float | None = Field(None, gt=0.0)  # beyond: no measurement (0)
    odometry_drift_per_m: float = Field(0.0, ge=0.0, le=0.5)  # position random walk, m per sqrt(m)
    heading_drift_per_rad: float = Field(0.0, ge=0.0, le=0.5)  # heading random walk per rad turned
    imu_bias_rad_per_s: float = Field(0.0, ge=0.0, le=0.1)  # slow IMU heading drift with motion time


class SensorNoise:
    """Applies :class:`SensorNoiseConfig` to depth images and to the reported pose."""

    def __init__(self, config: SensorNoiseConfig):
        self.config = config
        self._rng = np.random.default_rng(config.seed)
        self._offset = np.zeros(3)  # odometry - truth, in world axes
        self._heading_offset = 0.0
        self._imu_offset = 0.0

    @property
    def enabled(self) -> bool:
        c = self.config
        return any((c.depth_noise_rel, c.depth_hole_fraction, c.depth_max_m, c.odometry_drift_per_m, c.heading_drift_per_rad, c.imu_bias_rad_per_s))

    def reset(self, true_pose: Pose) -> None:
        self._offset[:] = 0.0
        self._heading_offset = 0.0
        self._imu_offset = 0.0

    def depth(self, depth_m: np.ndarray) -> np.ndarray:
        c = self.config
        if not (c.depth_noise_rel or c.depth_hole_fraction or c.depth_max_m):
            return depth_m
        d = depth_m.copy()
        valid = d > 0
        if c.depth_noise_rel:
            d[valid] += (c.depth_noise_rel * d[valid] ** 2 * self._rng.standard_normal(int(valid.sum()))).astype(np.float32)
            d[d < 0] = 0.0
        if c.depth_max_m:
            d[d > c.depth_max_m] = 0.0
        if c.depth_hole_fraction:
            d[self._rng.random(d.shape) < c.depth_hole_fraction] = 0.0
        return d

    def on_motion(self, distance_m: float, turned_rad: float) -> None:
        c = self.config
        if c.odometry_drift_per_m and distance_m > 0:
            self._offset[:2] += self._rng.standard_normal(2) * c.odometry_drift_per_m * math.sqrt(distance_m)
        if c.heading_drift_per_rad and turned_rad > 0:
            self._heading_offset += float(self._rng.standard_normal()) * c.heading_drift_per_rad * math.sqrt(turned_rad)
        if c.imu_bias_rad_per_s:
            # Treat one metre or one radian of motion as about a second of integration.
            self._imu_offset += c.imu_bias_rad_per_s * (distance_m + turned_rad)

    def odometry(self, true_pose: Pose) -> Pose:
        if not (self._offset.any() or self._heading_offset):
            return true_pose
        p = true_pose.xyz + self._offset
        return Pose(position_m=tuple(float(v) for v in p), heading_rad=float(wrap_angle(true_pose.heading_rad + self._heading_offset)))

    def imu_heading(self, true_heading_rad: float) -> float:
        return float(wrap_angle(true_heading_rad + self._heading_offset + self._imu_offset))
