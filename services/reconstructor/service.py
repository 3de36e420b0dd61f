"""reconstructor service: collects recorded tours, builds grounded maps, owns the map store.

* subscribes to every robot's tour frames (``IO_FRAMES``) and keeps them per recording;
* ``MAP_BUILD``: accepts a build job (:mod:`shared.jobs`); the job (``core.build_job``) waits for the
  recordings to be complete, reconstructs, aligns and integrates them, stores the map atomically and
  announces it on ``MAP_UPDATED``, reporting its progress on ``MAP_BUILD_EVENTS``;
* ``MAP_BUILD_CANCEL``: cancels a build of the key's map (the mapper's, when its exploration is
  cancelled); the build stops at its next region and stores nothing;
* ``MAP_LIST`` / ``MAP_INFO`` / ``MAP_CHUNK`` / ``MAP_IMPORT``: the map store over the bus.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict

from typing import Any

from pydantic import Field, model_validator

from libs.scenegraph.labeller import LABELLERS
from shared.cloud import CloudFormatError
from services.reconstructor.core import (
    DEFAULT_RECONSTRUCTOR, MapNotFoundError, MapStore, ReconstructionConfig,
)
from services.reconstructor.core.build_job import build_map
from services.reconstructor.core.uploads import Uploads
from shared import keys
from shared.bus.typed import NotFound
from shared.jobs import JobRunner
from shared.runner import Node, Service, ServiceSettings
from shared.schemas import (
    BuildCancelRequest, BuildMapRequest, Frame, JobAccepted, MapChunk, MapChunkRequest, MapImportProgress,
    MapImportRequest, MapInfo, SceneGraph, SceneGraphRequest, MapListReply, MapRequest, Ping,
)

log = logging.getLogger(__name__)


class ReconstructorSettings(ServiceSettings):
    store_dir: str = Field("runs/maps", description="where maps are stored (a volume in production)")
    frame_buffer_mb: int = Field(2048, ge=16, description="recorded frames kept in memory, all recordings")
    frames_timeout_s: float = Field(30.0, gt=0, description="wait this long for a recording's last frames")
    merge_voxel_m: float = Field(0.03, gt=0, le=1.0)
    max_queued_builds: int = Field(4, ge=1, le=100, description="map builds waiting behind the running one")
    max_open_uploads: int = Field(8, ge=1, le=1000, description="uploads in parts being received at once")
    upload_idle_s: float = Field(300.0, gt=0, le=86400, description="an upload with no part for this long is dropped")
    labeller: str = Field("sim", description=(
        "who names the rooms of each map version's scene graph (libs.scenegraph.labeller): sim (the map's "
        "semantic labels: a simulator or an upstream detector), none (unnamed rooms) or mllm (asks the chat "
        "model of labeller_config once per region with a few of its tour frames; answers cached per map)"))
    labeller_config: dict[str, Any] = Field(default_factory=dict, description=(
        'the labeller\'s typed config, e.g. {"model": "gpt-4o-mini", "base_url": "http://127.0.0.1:8088/v1", '
        '"api_key_env": "OPENAI_API_KEY", "frames_per_region": 3}'))

    @model_validator(mode="after")
    def _labeller_known(self):
        LABELLERS.create(self.labeller, self.labeller_config or None)  # an unknown name or bad config fails at start
        return self


class FrameBuffer:
    """Frames per recording, oldest recordings dropped first when over the memory budget."""

    def __init__(self, budget_bytes: int):
        self.budget = budget_bytes
        self._lock = threading.Condition()
        self._recs: OrderedDict[str, dict[int, Frame]] = OrderedDict()
        self._bytes = 0

    @staticmethod
    def _size(f: Frame) -> int:
        return sum(a.nbytes for a in (f.rgb, f.depth_m, f.semantic) if a is not None)

    def add(self, recording: str, frame: Frame) -> None:
        with self._lock:
            frames = self._recs.setdefault(recording, {})
            if frame.index in frames:
                return  # a duplicate delivery
            frames[frame.index] = frame
            self._bytes += self._size(frame)
            while self._bytes > self.budget and len(self._recs) > 1:
                old, dropped = self._recs.popitem(last=False)
                self._bytes -= sum(self._size(f) for f in dropped.values())
                log.warning("frame buffer full: dropped recording %s (%d frames)", old, len(dropped))
            self._lock.notify_all()

    def wait(self, recording: str, count: int, timeout_s: float) -> list[Frame]:
        """The recording's frames in order, once ``count`` arrived (or what there is at the deadline)."""
        end = time.monotonic() + timeout_s
        with self._lock:
            while len(self._recs.get(recording, {})) < count:
                left = end - time.monotonic()
                if left <= 0:
                    break
                self._lock.wait(left)
            frames = self._recs.get(recording, {})
            return [frames[i] for i in sorted(frames)]

    def drop(self, recording: str) -> None:
        with self._lock:
            frames = self._recs.pop(recording, {})
            self._bytes -= sum(self._size(f) for f in frames.values())


class ReconstructorService(Service[ReconstructorSettings]):
    name = "reconstructor"
    Settings = ReconstructorSettings

    def __init__(self, settings: ReconstructorSettings):
        super().__init__(settings)
        self.store = MapStore(settings.store_dir,
                              labeller=LABELLERS.create(settings.labeller, settings.labeller_config or None))
        self.frames = FrameBuffer(settings.frame_buffer_mb * 1024 * 1024)
        # Beside the maps (same disk, so the finished file is parsed where it lies); a dot name is no map.
        self.uploads = Uploads(self.store.root / ".uploads", max_open=settings.max_open_uploads,
                               idle_s=settings.upload_idle_s)
        self._node: Node | None = None
        self._builds: JobRunner | None = None
        self._build_maps: dict[str, str] = {}  # build id -> its map, for the builds queued or running
        self._build_lock = threading.Lock()

    def backends(self) -> dict[str, str]:
        return {"reconstruction": DEFAULT_RECONSTRUCTOR, "store": str(self.store.root),
                "labeller": self.store.labeller.name}

    def start(self, node: Node) -> None:
        self._node = node
        # Load (or compile) the fusion kernels now rather than inside the first map build.
        from services.reconstructor.core.kernels import warm_up

        warm_up()
        node.own(node.bus.subscribe(keys.IO_FRAMES.pattern(), Frame, self._on_frame))
        node.serve(keys.MAP_LIST.format(), Ping, self.list_maps)
        # Every handler on a map's key takes the map from the key (keyed=True); a payload map_id that
        # disagrees is refused (shared.keys.agree), so a request on map A's key never touches map B.
        node.serve(keys.MAP_INFO.pattern(), MapRequest, self.info, keyed=True)
        node.serve(keys.MAP_CHUNK.pattern(), MapChunkRequest, self.chunk, keyed=True)
        node.serve(keys.MAP_SCENE_GRAPH.pattern(), SceneGraphRequest, self.scene_graph, keyed=True)
        node.serve(keys.MAP_IMPORT.pattern(), MapImportRequest, self.import_map, workers=1, keyed=True)
        # One build at a time: reconstruction holds every frame of an exploration in memory.
        self._builds = JobRunner(node.bus, name="map build", workers=1,
                                 max_queued=self.settings.max_queued_builds)
        node.serve(keys.MAP_BUILD.pattern(), BuildMapRequest, self.build, workers=1, keyed=True)
        node.serve(keys.MAP_BUILD_CANCEL.pattern(), BuildCancelRequest, self.cancel_build, workers=1, keyed=True)

    def stop(self) -> None:
        if self._builds is not None:
            self._builds.close()

    def _on_frame(self, key: str, frame: Frame) -> None:
        try:
            recording = keys.ids_of(keys.IO_FRAMES, key)["recording"]
        except keys.KeyExprError:
            log.warning("frame on %r dropped: not a concrete %s key", key, keys.IO_FRAMES.template)
            return
        self.frames.add(recording, frame)

    # --- the store -----------------------------------------------------------------------------------
    def list_maps(self, _: Ping) -> MapListReply:
        return MapListReply(maps=self.store.list())

    def _map_query(self, key_def, key: str, req, read):
        """A read of one stored map: the map is the key's (a payload id that disagrees is refused) and a
        map or version the store lacks is answered ``not_found``."""
        keys.agree(key_def, key, req, map="map_id")
        try:
            return read()
        except MapNotFoundError as exc:
            raise NotFound(str(exc)) from None

    def info(self, key: str, req: MapRequest) -> MapInfo:
        return self._map_query(keys.MAP_INFO, key, req, lambda: self.store.info(req.map_id, req.version))

    def scene_graph(self, key: str, req: SceneGraphRequest) -> SceneGraph:
        return self._map_query(keys.MAP_SCENE_GRAPH, key, req,
                               lambda: self.store.scene_graph(req.map_id, req.version))

    def chunk(self, key: str, req: MapChunkRequest) -> MapChunk:
        return self._map_query(keys.MAP_CHUNK, key, req,
                               lambda: self.store.chunk(req.map_id, req.version, req.index, req.max_points))

    def import_map(self, key: str, req: MapImportRequest) -> MapInfo | MapImportProgress:
        try:
            keys.agree(keys.MAP_IMPORT, key, req, map="map_id")
        except keys.KeyExprError:
            if req.upload_id is not None:  # any failure drops the whole upload (MapImportRequest)
                self.uploads.drop(req.upload_id, req.filename)
            raise
        if req.upload_id is None:  # whole in one request
            return self._import(req, req.data)
        if req.abort:
            self.uploads.drop(req.upload_id, req.filename)
            return MapImportProgress(upload_id=req.upload_id, received_bytes=0)
        received = self.uploads.append(req.upload_id, req.map_id, req.filename, req.offset, req.data)
        if not req.last:
            return MapImportProgress(upload_id=req.upload_id, received_bytes=received)
        try:
            return self._import(req, self.uploads.path(req.upload_id, req.filename))
        finally:
            self.uploads.drop(req.upload_id, req.filename)

    def _import(self, req: MapImportRequest, data) -> MapInfo:
        try:
            info = self.store.import_cloud(req.map_id, data, filename=req.filename)
        except CloudFormatError as exc:
            # An unreadable upload is the sender's fault: bad_request (HTTP 422), not internal (502).
            raise ValueError(f"{req.filename}: {exc}") from exc
        self._announce(info)
        return info

    def _announce(self, info: MapInfo) -> None:
        self._node.bus.publish(keys.MAP_UPDATED.format(map=info.map_id), info)

    # --- building ------------------------------------------------------------------------------------
    def build(self, key: str, req: BuildMapRequest) -> JobAccepted:
        keys.agree(keys.MAP_BUILD, key, req, map="map_id")
        if not req.recordings:
            raise ValueError("a build needs at least one recording")
        s = self.settings
        config = ReconstructionConfig.model_validate(
            {"backend": req.reconstruction, "merge_voxel_m": s.merge_voxel_m, **req.options})
        assert self._builds is not None
        with self._build_lock:
            reply = self._builds.submit(req.build_id, lambda ctx: build_map(
                ctx, req, frames=self.frames, store=self.store, config=config, announce=self._announce,
                frames_timeout_s=s.frames_timeout_s), keys.MAP_BUILD_EVENTS.format(map=req.map_id, build=req.build_id))
            if reply.accepted:
                active = set(self._builds.active())
                self._build_maps = {b: m for b, m in self._build_maps.items() if b in active}
                self._build_maps[req.build_id] = req.map_id
        return reply

    def cancel_build(self, key: str, req: BuildCancelRequest) -> JobAccepted:
        """Cancel a queued or running build of the key's map: a request on map X's key cannot stop
        another map's build."""
        found = keys.ids_of(keys.MAP_BUILD_CANCEL, key)
        assert self._builds is not None
        with self._build_lock:
            mine = self._build_maps.get(req.build_id) == found["map"]
        if not mine:
            return JobAccepted(job_id=req.build_id, accepted=False, reason=f"no such build of map {found['map']} here")
        return self._builds.cancel(req.build_id)
