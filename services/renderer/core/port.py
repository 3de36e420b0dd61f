"""One indexed map behind the planner's renderer port (views + spatial map as bus results).

The renderer service wraps each cached map in a :class:`MapRenderer`; tests and benchmarks use the
same class in-process, so the step they measure is the step the service runs.
"""

from __future__ import annotations

import time

import numpy as np

from shared.schemas import CameraIntrinsics, Candidate, Pose, RenderResult, SpatialMapResult, ViewPose

from .cloud import IndexedCloud
from .spatial_map import SpatialMapper
from .splat import SplatRenderer


class MapRenderer:
    def __init__(self, index: IndexedCloud, renderer: SplatRenderer, mapper: SpatialMapper,
                 map_id: str = "local", version: int = 1):
        self.index, self.renderer, self.mapper = index, renderer, mapper
        self.map_id, self.version = map_id, version

    def views(self, map_id: str, views: list[ViewPose], camera: CameraIntrinsics | None = None,
              with_labels: bool = True, camera_height_m: float = 1.25) -> RenderResult:
        t0 = time.perf_counter()
        out = self.renderer.render(self.index, views, camera or CameraIntrinsics(), camera_height_m, with_labels)
        return RenderResult(map_id=self.map_id, version=self.version, rgb=out.rgb, depth_m=out.depth_m,
                            hole_mask=out.hole_mask, labels=out.labels if with_labels else None,
                            render_s=time.perf_counter() - t0)

    def spatial_map(self, map_id: str, pose: Pose, trajectory_m: np.ndarray | None = None,
                    candidates: list[Candidate] | None = None, agent_up: bool = False, size_px: int = 512,
                    radius_m: float | None = None) -> SpatialMapResult:
        t0 = time.perf_counter()
        img = self.mapper.draw(self.index, pose, trajectory_m, candidates or [], agent_up, size_px, radius_m)
        return SpatialMapResult(map_id=self.map_id, version=self.version, image=img.image,
                                metres_per_px=img.metres_per_px, render_s=time.perf_counter() - t0)
