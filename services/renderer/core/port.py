"""One indexed map behind the planner's renderer port (views + spatial map as bus results).

The renderer service wraps each cached map in a :class:`MapRenderer`; tests and benchmarks use the
same class in-process, so the step they measure is the step the service runs.
"""

from __future__ import annotations

import time

import numpy as np

from libs.pointrender.cloud import IndexedCloud
from libs.pointrender.splat import SplatRenderer
from shared.schemas import CameraIntrinsics, Candidate, Pose, RenderResult, SpatialMapResult, ViewPose

from .errors import MapMismatchError
from .floors import floors_of
from .spatial_map import SpatialMapper


class MapRenderer:
    """Views and spatial maps of one map. ``map_id`` None: an in-process port serving its one map
    under whatever id it is asked for; otherwise a request for another id is refused."""

    def __init__(self, index: IndexedCloud, renderer: SplatRenderer, mapper: SpatialMapper,
                 map_id: str | None = None, version: int = 1):
        self.index, self.renderer, self.mapper = index, renderer, mapper
        self.map_id, self.version = map_id, version

    def _check(self, map_id: str) -> str:
        if self.map_id is not None and map_id != self.map_id:
            raise MapMismatchError(f"this renderer serves map {self.map_id!r}, not {map_id!r}")
        return map_id

    def on_floor(self, views: list[ViewPose], search_m: float) -> list[ViewPose]:
        """Each view moved to the map's standing surface under it nearest to its z (within
        ``search_m``): a candidate on the stairs or another floor is seen from its own height."""
        if search_m <= 0:
            return list(views)
        floors = floors_of(self.index)
        out = []
        for v in views:
            x, y, z = v.position_m
            out.append(v.model_copy(update={"position_m": (x, y, floors.floor_z(x, y, z, search_m))}))
        return out

    def views(self, map_id: str, views: list[ViewPose], camera: CameraIntrinsics | None = None,
              with_labels: bool = True, camera_height_m: float = 1.25, floor_search_m: float = 1.5) -> RenderResult:
        t0 = time.perf_counter()
        map_id = self._check(map_id)
        views = self.on_floor(views, floor_search_m)
        out = self.renderer.render(self.index, views, camera or CameraIntrinsics(), camera_height_m, with_labels)
        return RenderResult(map_id=map_id, version=self.version, rgb=out.rgb, depth_m=out.depth_m,
                            hole_mask=out.hole_mask, labels=out.labels if with_labels else None,
                            splat_mode=self.renderer.config.mode, render_s=time.perf_counter() - t0)

    def spatial_map(self, map_id: str, pose: Pose, trajectory_m: np.ndarray | None = None,
                    candidates: list[Candidate] | None = None, agent_up: bool = False, size_px: int = 512,
                    radius_m: float | None = None, room_labels=None) -> SpatialMapResult:
        t0 = time.perf_counter()
        map_id = self._check(map_id)
        rooms = None if room_labels is None else [(r.name, r.x_m, r.y_m) for r in room_labels]
        img = self.mapper.draw(self.index, pose, trajectory_m, candidates or [], agent_up, size_px, radius_m,
                               room_labels=rooms)
        return SpatialMapResult(map_id=map_id, version=self.version, image=img.image,
                                metres_per_px=img.metres_per_px, render_s=time.perf_counter() - t0)
