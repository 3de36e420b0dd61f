"""renderer service: anticipated views and spatial maps from stored maps.

Maps are fetched from the map store (the reconstructor) by id in chunks and indexed once per
(map, version); ``MAP_UPDATED`` tells us when "latest" may have moved. An announcement is only a
hint - anyone on the bus can publish one - so its version is never taken on trust: it makes the next
request for "latest" ask the store again, and a version the store does not hold is never used.
Several renderer instances can run side by side: each serves the same keys and keeps its own cache.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from typing import Any

from pydantic import Field

from services.renderer.core import MapRenderer, SpatialMapper
from shared import keys
from shared.bus.typed import NotFound, RemoteError
from shared.clients import MapClient
from shared.cloud import PointCloud
from libs.pointrender import RENDERERS, IndexedCloud
from shared.runner import Node, Service, ServiceSettings
from shared.schemas import (
    ErrorCode,
    MapInfo,
    RenderRequest,
    RenderResult,
    SpatialMapRequest,
    SpatialMapResult,
)

log = logging.getLogger(__name__)


class RendererSettings(ServiceSettings):
    splat_backend: str = Field("numpy", description="splatting backend: numpy or torch (CUDA when present)")
    splat_config: dict[str, Any] = Field(default_factory=dict)
    cache_maps: int = Field(4, ge=1, le=64, description="indexed maps kept in memory")


class MapCache:
    """(map_id, version) -> IndexedCloud, least recently used out; one fetch per key at a time."""

    def __init__(self, maps: MapClient, capacity: int, prepare=None):
        self.maps, self.capacity = maps, capacity
        # Called on each newly indexed map, once, before any request renders it (the renderer's
        # per-map data: the per-point spacing of the visibility mode takes seconds at 1e6 points).
        self.prepare = prepare
        self._lock = threading.Lock()
        self._items: OrderedDict[tuple[str, int], IndexedCloud] = OrderedDict()
        self._latest: dict[str, int] = {}
        self._fetching: dict[tuple[str, int], threading.Lock] = {}

    def forget_latest(self, map_id: str) -> None:
        """Latest may have moved (a ``MAP_UPDATED`` announcement): the next request asks the store."""
        with self._lock:
            self._latest.pop(map_id, None)

    def _latest_version(self, map_id: str) -> int:
        version = self._latest.get(map_id)
        if version is None:
            version = self._info(map_id, None).version  # the store's word, never an announcement's
            with self._lock:
                self._latest[map_id] = version
        return version

    def get(self, map_id: str, version: int | None) -> tuple[IndexedCloud, int]:
        if version is not None:
            return self._get(map_id, version)
        try:
            return self._get(map_id, self._latest_version(map_id))
        except NotFound:
            # The version we took for latest is gone from the store: ask it again, once.
            self.forget_latest(map_id)
            return self._get(map_id, self._latest_version(map_id))

    def _get(self, map_id: str, version: int) -> tuple[IndexedCloud, int]:
        key = (map_id, version)
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key], version
            fetch_lock = self._fetching.setdefault(key, threading.Lock())
        with fetch_lock:  # concurrent requests for a new map wait for one fetch
            with self._lock:
                if key in self._items:
                    return self._items[key], version
            try:
                info = self._info(map_id, version)
                t0 = time.perf_counter()
                cloud = PointCloud.from_chunks(self.maps.chunks(map_id, version), info.label_names)
                index = IndexedCloud(cloud)
                if self.prepare is not None:
                    self.prepare(index)
            except BaseException:
                with self._lock:  # a version that does not exist leaves nothing behind
                    self._fetching.pop(key, None)
                raise
            log.info("indexed map %s v%d: %d points in %.2f s", map_id, version, len(cloud.xyz),
                     time.perf_counter() - t0)
            with self._lock:
                self._items[key] = index
                while len(self._items) > self.capacity:
                    self._items.popitem(last=False)
                self._fetching.pop(key, None)
        return index, version

    def _info(self, map_id: str, version: int | None) -> MapInfo:
        try:
            return self.maps.info(map_id, version)
        except RemoteError as exc:
            if exc.code == ErrorCode.NOT_FOUND:
                raise NotFound(f"no map {map_id!r}" + (f" version {version}" if version else "")) from None
            raise


class RendererService(Service[RendererSettings]):
    name = "renderer"
    Settings = RendererSettings

    def __init__(self, settings: RendererSettings):
        super().__init__(settings)
        self.renderer = RENDERERS.create(settings.splat_backend, settings.splat_config or None)
        # A request may ask for another splat mode (the ablation of paper vs visibility views runs on one
        # system): one renderer per mode, the other made on first use, same backend and parameters.
        self._by_mode = {self.renderer.config.mode: self.renderer}
        self._by_mode_lock = threading.Lock()
        self.mapper = SpatialMapper()
        self.cache: MapCache | None = None

    def backends(self) -> dict[str, str]:
        return {"splat": self.settings.splat_backend}

    def start(self, node: Node) -> None:
        # Compile the splatting kernels now, not on the first request of a mission.
        log.info("renderer kernels ready in %.2f s", self.renderer.warm_up())
        self.cache = MapCache(MapClient(node.bus), self.settings.cache_maps, prepare=self.renderer.prepare)
        # Only the map id of the key is used: what the announcement claims is checked with the store.
        node.own(node.bus.subscribe(keys.MAP_UPDATED.pattern(), MapInfo, self._on_map_updated))
        node.serve(keys.RENDER_VIEWS.format(), RenderRequest, self.views, replicated=True)
        node.serve(keys.RENDER_MAP.format(), SpatialMapRequest, self.spatial_map, replicated=True)

    def _on_map_updated(self, key: str, _info: MapInfo) -> None:
        try:
            map_id = keys.ids_of(keys.MAP_UPDATED, key)["map"]
        except keys.KeyExprError:
            log.warning("map announcement on %r ignored: not a concrete %s key", key, keys.MAP_UPDATED.template)
            return
        self.cache.forget_latest(map_id)

    def _renderer(self, mode: str | None):
        if mode is None:
            return self.renderer
        with self._by_mode_lock:
            if mode not in self._by_mode:
                config = {**(self.settings.splat_config or {}), "mode": mode}
                renderer = RENDERERS.create(self.settings.splat_backend, config)
                log.info("renderer for splat mode %r ready in %.2f s", mode, renderer.warm_up())
                self._by_mode[mode] = renderer
            return self._by_mode[mode]

    def _map(self, map_id: str, version: int | None, mode: str | None = None) -> MapRenderer:
        index, version = self.cache.get(map_id, version)
        return MapRenderer(index, self._renderer(mode), self.mapper, map_id, version)

    def views(self, req: RenderRequest) -> RenderResult:
        return self._map(req.map_id, req.version, req.splat_mode).views(req.map_id, req.views, req.camera, req.with_labels,
                                                         req.camera_height_m, req.floor_search_m)

    def spatial_map(self, req: SpatialMapRequest) -> SpatialMapResult:
        return self._map(req.map_id, req.version).spatial_map(req.map_id, req.pose, req.trajectory_m, req.candidates,
                                                               req.agent_up, req.size_px, req.radius_m,
                                                               room_labels=req.room_labels)
