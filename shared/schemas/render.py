"""The renderer's requests and results."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from shared.arrays import Array

from .base import SegmentId, _finite_array, BudgetExceeded, Message, PATH_MAX_POINTS, RENDER_MAX_PIXELS, WORLD_LIMIT_M
from .geometry import CameraIntrinsics, Pose, ViewPose
from .navigation import Candidate


# --- renderer --------------------------------------------------------------------------------------


# The renderer's splat modes (libs.pointrender.splat.SplatConfig.mode): the paper's fixed 3x3
# Gaussian, or the occlusion-correct visibility splatting with hole filling (issue 20).
SplatMode = Literal["paper", "visibility"]


class RenderRequest(Message):
    """Anticipated views of one step: every candidate's view in one request."""

    map_id: SegmentId
    version: int | None = Field(None, ge=1, le=2**31 - 1)
    views: list[ViewPose] = Field(min_length=1, max_length=64)
    camera: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    camera_height_m: float = Field(1.25, ge=0.0, le=3.0)
    with_labels: bool = True
    # Each view stands on the map's floor under it nearest to its given z, within this range (a
    # candidate on the stairs or another storey is seen from its own height); 0 keeps z as given.
    floor_search_m: float = Field(1.5, ge=0.0, le=5.0)
    splat_mode: SplatMode | None = None  # None: the renderer's configured mode

    def check_budget(self) -> None:
        px = len(self.views) * self.camera.width_px * self.camera.height_px
        if px > RENDER_MAX_PIXELS:
            raise BudgetExceeded("rendered pixels (views x width x height)", px, RENDER_MAX_PIXELS, "px")


class RenderResult(Message):
    map_id: SegmentId
    version: int
    rgb: Array("uint8", 4, 3)  # (B, H, W, 3)
    depth_m: Array("float32", 3)
    hole_mask: Array("bool", 3)
    labels: Array("int32", 3) | None = None
    render_s: float = 0.0
    splat_mode: SplatMode | None = None  # the mode that rendered these views (None: not said)


class MapRoomLabel(Message):
    """A room name to draw on the spatial map at a floor position (from the map's scene graph, issue 32)."""

    name: str = Field(min_length=1, max_length=64)
    x_m: float = Field(ge=-WORLD_LIMIT_M, le=WORLD_LIMIT_M)
    y_m: float = Field(ge=-WORLD_LIMIT_M, le=WORLD_LIMIT_M)


class SpatialMapRequest(Message):
    map_id: SegmentId
    version: int | None = Field(None, ge=1, le=2**31 - 1)
    pose: Pose
    trajectory_m: Array("float64", 2) | None = None  # (T, 3)
    candidates: list[Candidate] = Field(default_factory=list, max_length=1000)
    agent_up: bool = False
    size_px: int = Field(512, ge=64, le=2048)
    radius_m: float | None = Field(None, gt=0.0, le=WORLD_LIMIT_M)  # None: the whole floor
    # Room instances to name ("bedroom 2"), e.g. the scene graph's; None: the cloud's room labels.
    room_labels: list[MapRoomLabel] | None = Field(None, max_length=10_000)

    @model_validator(mode="after")
    def _trajectory(self):
        t = self.trajectory_m
        if t is not None and t.size:
            if t.ndim != 2 or t.shape[1] != 3:
                raise ValueError(f"trajectory_m must be (T, 3), got {t.shape}")
            _finite_array(t, "trajectory_m")
            if np.abs(t).max() > WORLD_LIMIT_M:
                raise ValueError(f"trajectory_m: coordinates beyond +-{WORLD_LIMIT_M:.0f} m")
        return self

    def check_budget(self) -> None:
        n = 0 if self.trajectory_m is None else len(self.trajectory_m)
        if n > PATH_MAX_POINTS:
            raise BudgetExceeded("trajectory points", n, PATH_MAX_POINTS, "points")


class SpatialMapResult(Message):
    map_id: SegmentId
    version: int
    image: Array("uint8", 3, 3)
    metres_per_px: float
    render_s: float = 0.0
