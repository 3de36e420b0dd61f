"""Downloads: a job's Rerun recording and trajectory CSV; a map as PCD or a Nav2 map (PGM + YAML).

Formats are written by :mod:`shared.recording` and :mod:`shared.export`; this router only gathers
their input (stored events, map chunks over the bus) and streams the bytes.

Recordings: a job is recorded when its request says ``record: true``, or says nothing and the
gateway's ``record_jobs`` setting is on. :class:`RecordingWriter` writes ``<recordings_dir>/<id>.rrd``
as soon as a recorded job ends (from the stored events and the map cloud of that moment); a GET for a
recorded job whose file is missing (the gateway was down when it ended) writes it then.
"""

from __future__ import annotations

import io
import logging
import queue
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path as FsPath
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import BaseModel

from services.gateway.deps import BusDep, SettingsDep, StoreDep
from services.gateway.errors import GatewayError, ask
from services.gateway.params import JobId, MapId, Version
from services.gateway.records import TERMINAL, JobKind
from services.gateway.settings import GatewaySettings
from services.gateway.store import GatewayStore, JobRow
from shared import keys
from shared.bus.base import Closeable
from shared.bus.typed import RemoteError, TypedBus
from shared.export import OccupancyConfig, nav2_files, occupancy_from_cloud
from shared.export.nav2 import EmptyMapError
from shared.export.pcd import pcd_header, pcd_records, record_size
from shared.export.trajectory import trajectory_csv
from shared.recording import RecordedEvent, RecordingInput, write_recording
from shared.clients import MapClient
from shared.schemas import JobEvent, JobEventKind, MapChunk, MapInfo

log = logging.getLogger(__name__)
router = APIRouter(tags=["downloads"])
_RRD = {200: {"content": {"application/octet-stream": {}}, "description": "Rerun recording (.rrd)"},
        404: {}, 409: {}, 503: {}}


# --- gathering ---------------------------------------------------------------------------------------


def job_events(store: GatewayStore, job_id: str, with_images: bool = True, batch: int = 500) -> list[RecordedEvent]:
    """Every stored event of a job, payloads as stored (JSON), images included."""
    out: list[RecordedEvent] = []
    after = -1
    while True:
        rows = store.events(job_id, after, batch)
        for ev in rows:
            images = {}
            if with_images:
                for name in ev.image_names:
                    data = store.image(job_id, ev.seq, name)
                    if data is not None:
                        images[name] = data
            out.append(RecordedEvent(ev.seq, JobEventKind(ev.kind), ev.state, ev.step, ev.timestamp_s, ev.data, images))
        if len(rows) < batch:
            return out
        after = rows[-1].seq


def map_chunks(bus: TypedBus, settings: GatewaySettings, map_id: str, version: int | None) -> Iterator[MapChunk]:
    """The map's chunks in order, all of the first chunk's version (raises RemoteError)."""
    return MapClient(bus, timeout_s=settings.request_timeout_s).chunks(map_id, version, settings.map_chunk_points)


def map_cloud(bus: TypedBus, settings: GatewaySettings, map_id: str,
              version: int | None) -> tuple[np.ndarray, np.ndarray, int]:
    chunks = list(map_chunks(bus, settings, map_id, version))
    xyz = np.concatenate([c.xyz_m for c in chunks]) if chunks else np.zeros((0, 3), np.float32)
    rgb = np.concatenate([c.rgb for c in chunks]) if chunks else np.zeros((0, 3), np.uint8)
    return xyz, rgb, chunks[0].version


# --- recordings ----------------------------------------------------------------------------------------


def recorded(row: JobRow, settings: GatewaySettings) -> bool:
    """Whether the job asked to be recorded (``record`` in its request), else the gateway's setting."""
    req = row.request
    flag = (req.get("options") or {}).get("record") if row.kind == JobKind.MISSION else req.get("record")
    return settings.record_jobs if flag is None else bool(flag)


def recording_path(settings: GatewaySettings, job_id: str) -> FsPath:
    folder = settings.recordings_dir or FsPath(settings.db_path).parent / "recordings"
    return FsPath(folder) / f"{job_id}.rrd"


def write_job_recording(store: GatewayStore, bus: TypedBus, settings: GatewaySettings, row: JobRow) -> FsPath:
    """Write the job's ``.rrd`` from its stored events and (when the map can be had) its map's cloud."""
    events = job_events(store, row.id)
    map_id = row.request.get("map_id") or (row.summary.get("map_id") if row.summary else None)
    xyz = rgb = None
    info: dict = {"state": row.state.value}
    if row.kind == JobKind.MISSION:
        info["instruction"] = row.request.get("instruction", "")
    # A mission's map is the one it navigated; an exploration's is the map it built (once it has).
    if map_id and settings.recording_max_points > 0:
        try:
            xyz, rgb, version = map_cloud(bus, settings, map_id, None)
            info["map version"] = version
        except RemoteError as exc:
            log.warning("recording %s without its map %s: %s", row.id, map_id, exc)
            info["map"] = f"not available when recorded ({exc})"
    graph = None
    if map_id:
        # The map's scene graph (issue 32) of the version recorded (the latest when the cloud was not read).
        try:
            graph = MapClient(bus, timeout_s=settings.request_timeout_s).scene_graph(map_id, info.get("map version"))
        except Exception as exc:  # a store without graphs, a timeout: the recording is still worth writing
            log.warning("recording %s without the scene graph of %s: %s", row.id, map_id, exc)
    inp = RecordingInput(job_id=row.id, job_kind=row.kind.value, events=events, cloud_xyz_m=xyz, cloud_rgb=rgb,
                         map_id=map_id or "", info=info, options=row.request.get("options") or {},
                         scene_graph=graph)
    t0 = time.perf_counter()
    path = write_recording(inp, recording_path(settings, row.id), max_points=max(1, settings.recording_max_points))
    log.info("recorded %s %s: %d events, %d map points, %.1f s -> %s", row.kind.value, row.id, len(events),
             0 if xyz is None else len(xyz), time.perf_counter() - t0, path)
    return path


class RecordingWriter:
    """Writes each recorded job's ``.rrd`` when the job ends, on one worker thread.

    It listens to the same event keys as the ingest; a terminal event queues the job, and the worker
    waits (bounded) until the store holds the job as ended with every event, then writes the file.
    """

    def __init__(self, bus: TypedBus, store: GatewayStore, settings: GatewaySettings, settle_s: float = 10.0):
        self.bus, self.store, self.settings, self.settle_s = bus, store, settings, settle_s
        self.written = 0
        self._queue: queue.Queue[tuple[str, int] | None] = queue.Queue(maxsize=1000)
        self._locks: dict[str, threading.Lock] = {}
        self._lock = threading.Lock()
        # Set by close(): a worker waiting for a job to settle gives up at once, before the app closes the
        # store under it (it used to wait out settle_s, longer than close() waits for it).
        self._stopping = threading.Event()
        self._subs: list[Closeable] = [
            bus.subscribe(keys.MISSION_EVENTS.pattern(robot=settings.robot), JobEvent,
                          lambda k, ev: self._on_event(k, ev, keys.MISSION_EVENTS, "mission")),
            bus.subscribe(keys.EXPLORATION_EVENTS.pattern(robot=settings.robot), JobEvent,
                          lambda k, ev: self._on_event(k, ev, keys.EXPLORATION_EVENTS, "exploration")),
        ]
        self._worker = threading.Thread(target=self._work, name="recordings", daemon=True)
        self._worker.start()

    def _on_event(self, key: str, ev: JobEvent, template: keys.Key | None = None, part: str = "") -> None:
        if template is not None:
            try:  # the job is the key's: an event naming another job is not recorded under it
                keys.agree(template, key, ev, **{part: "job_id"})
            except keys.KeyExprError as exc:
                log.warning("recording trigger ignored: %s", exc)
                return
        if ev.state in TERMINAL:
            try:
                self._queue.put_nowait((ev.job_id, ev.seq))
            except queue.Full:  # written on the first GET instead
                log.warning("recording queue full: %s will be recorded when first downloaded", ev.job_id)

    def job_lock(self, job_id: str) -> threading.Lock:
        with self._lock:
            return self._locks.setdefault(job_id, threading.Lock())

    def _work(self) -> None:
        while (item := self._queue.get()) is not None:
            job_id, seq = item
            deadline = time.monotonic() + self.settle_s
            row = self.store.get_job(job_id)
            while (row is None or not row.terminal or row.last_seq < seq) and time.monotonic() < deadline:
                if self._stopping.wait(0.05):
                    return
                row = self.store.get_job(job_id)
            if row is None or not row.terminal or not recorded(row, self.settings):
                continue
            if recording_path(self.settings, job_id).is_file():
                continue  # a terminal event again (replayed from a publisher's cache after a restart)
            try:
                with self.job_lock(job_id):
                    write_job_recording(self.store, self.bus, self.settings, row)
                self.written += 1
            except Exception:  # noqa: BLE001 - one bad job must not stop the recorder
                log.exception("could not record %s", job_id)

    def close(self) -> None:
        self._stopping.set()
        for s in self._subs:
            s.close()
        self._subs.clear()
        self._queue.put(None)
        self._worker.join(10.0)


def _recording_response(kind: JobKind, job_id: str, request: Request, store: GatewayStore, bus: TypedBus,
                        settings: GatewaySettings) -> FileResponse:
    row = store.get_job(job_id, kind)
    if row is None:
        raise GatewayError(f"no {kind.value} {job_id!r}", 404)
    if not recorded(row, settings):
        where = "options.record" if kind == JobKind.MISSION else "record"
        raise GatewayError(f"{kind.value} {job_id!r} was not recorded: submit it with {where}: true, or run the "
                           "gateway with ANT_RECORD_JOBS=true", 404)
    path = recording_path(settings, job_id)
    if not path.is_file():
        if not row.terminal:
            raise GatewayError(f"{kind.value} {job_id!r} is {row.state.value}: its recording is written when it ends",
                               409)
        writer: RecordingWriter | None = getattr(request.app.state, "recordings", None)
        lock = writer.job_lock(job_id) if writer else threading.Lock()
        with lock:
            if not path.is_file():
                write_job_recording(store, bus, settings, row)
    return FileResponse(path, media_type="application/octet-stream", filename=f"{job_id}.rrd")


class Download(BaseModel):
    name: str
    url: str
    media_type: str
    available: bool
    reason: str = ""


class DownloadList(BaseModel):
    """What can be downloaded of one job, for the dashboard's download area."""

    items: list[Download]


def _job_downloads(kind: JobKind, job_id: str, store: GatewayStore, settings: GatewaySettings) -> DownloadList:
    row = store.get_job(job_id, kind)
    if row is None:
        raise GatewayError(f"no {kind.value} {job_id!r}", 404)
    base = f"/{kind.value}s/{job_id}"
    if not recorded(row, settings):
        why = "not recorded (submit with record: true, or set ANT_RECORD_JOBS=true)"
    elif not row.terminal and not recording_path(settings, job_id).is_file():
        why = f"written when the {kind.value} ends"
    else:
        why = ""
    items = [Download(name="Rerun recording (.rrd)", url=f"{base}/recording.rrd", media_type="application/octet-stream",
                      available=not why, reason=why)]
    if kind == JobKind.MISSION:
        items.append(Download(name="trajectory (.csv)", url=f"{base}/trajectory.csv", media_type="text/csv",
                              available=True))
    return DownloadList(items=items)


@router.get("/missions/{mission_id}/downloads", response_model=DownloadList, responses={404: {}})
def mission_downloads(mission_id: JobId, store: StoreDep, settings: SettingsDep) -> DownloadList:
    """The mission's downloads (recording, trajectory) and whether each is available yet."""
    return _job_downloads(JobKind.MISSION, mission_id, store, settings)


@router.get("/explorations/{exploration_id}/downloads", response_model=DownloadList, responses={404: {}})
def exploration_downloads(exploration_id: JobId, store: StoreDep, settings: SettingsDep) -> DownloadList:
    """The exploration's downloads (its recording) and whether each is available yet."""
    return _job_downloads(JobKind.EXPLORATION, exploration_id, store, settings)


@router.get("/missions/{mission_id}/recording.rrd", response_class=FileResponse, responses=_RRD)
def mission_recording(mission_id: JobId, request: Request, store: StoreDep, bus: BusDep,
                      settings: SettingsDep) -> FileResponse:
    """The mission as a Rerun recording: map cloud, trajectory, candidates and the chosen one, observed
    and anticipated views, spatial map, decisions and reasoning, per-step timings.
    Open it with ``python -m shared.recording open FILE`` (the viewer ships with rerun-sdk)."""
    return _recording_response(JobKind.MISSION, mission_id, request, store, bus, settings)


@router.get("/explorations/{exploration_id}/recording.rrd", response_class=FileResponse, responses=_RRD)
def exploration_recording(exploration_id: JobId, request: Request, store: StoreDep, bus: BusDep,
                          settings: SettingsDep) -> FileResponse:
    """The exploration as a Rerun recording: its progress, messages and the map it built."""
    return _recording_response(JobKind.EXPLORATION, exploration_id, request, store, bus, settings)


@router.get("/missions/{mission_id}/trajectory.csv", response_class=Response,
            responses={200: {"content": {"text/csv": {}}}, 404: {}})
def mission_trajectory(mission_id: JobId, store: StoreDep) -> Response:
    """One row per pose: step, x/y/z (world, metres, z up), heading, time, the action taken from it and
    the distance walked so far; the last row is the pose the mission ended at."""
    if store.get_job(mission_id, JobKind.MISSION) is None:
        raise GatewayError(f"no mission {mission_id!r}", 404)
    poses: list[dict] = []
    for ev in job_events(store, mission_id, with_images=False):
        d = ev.data
        pose = d.get("pose") or {}
        at = pose.get("position_m")
        if ev.kind == JobEventKind.FINISHED and d.get("trajectory_m"):
            at = d["trajectory_m"][-1]  # the pose after the last move
        if at is None or ev.kind not in (JobEventKind.STARTED, JobEventKind.STEP, JobEventKind.FINISHED):
            continue
        row = {"step": ev.step, "position_m": at, "heading_rad": pose.get("heading_rad"), "timestamp_s": ev.timestamp_s,
               "action": (d.get("decision") or {}).get("kind", "") if ev.kind == JobEventKind.STEP else ""}
        last = poses[-1] if poses else None
        if last is not None and list(last["position_m"]) == list(at) and ev.kind != JobEventKind.STEP:
            continue  # the end where the last step stopped: no new pose
        if last is not None and list(last["position_m"]) == list(at) and last.get("started"):
            poses[-1] = row  # the first step observed where the mission started: one row, with its action
            continue
        poses.append({**row, "started": ev.kind == JobEventKind.STARTED})
    return Response(trajectory_csv(poses), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="{mission_id}-trajectory.csv"'})


# --- maps ------------------------------------------------------------------------------------------------


def _map_info(bus: TypedBus, settings: GatewaySettings, map_id: str, version: int | None) -> MapInfo:
    return ask(f"map {map_id!r}", lambda: MapClient(bus, timeout_s=settings.request_timeout_s).info(map_id, version))


@router.get("/maps/{map_id}/cloud.pcd", response_class=StreamingResponse,
            responses={200: {"content": {"application/octet-stream": {}}, "description": "binary PCD v0.7"},
                       404: {}, 503: {}})
def map_pcd(map_id: MapId, bus: BusDep, settings: SettingsDep, version: Version = None) -> StreamingResponse:
    """The map's points as a binary PCD (x y z float, rgb packed as PCL does[, label uint]), streamed."""
    info = _map_info(bus, settings, map_id, version)
    chunks = map_chunks(bus, settings, map_id, info.version)
    first = ask(f"map {map_id!r}", lambda: next(chunks))
    with_labels = first.labels is not None
    header = pcd_header(info.point_count, with_labels)

    def body() -> Iterator[bytes]:
        yield header
        yield pcd_records(first.xyz_m, first.rgb, first.labels, with_labels)
        for c in chunks:  # an error here ends the stream short of Content-Length
            yield pcd_records(c.xyz_m, c.rgb, c.labels, with_labels)

    return StreamingResponse(body(), media_type="application/octet-stream", headers={
        "Content-Length": str(len(header) + info.point_count * record_size(with_labels)),
        "Content-Disposition": f'attachment; filename="{map_id}-v{first.version}.pcd"'})


FloorZ = Annotated[float | None, Query(ge=-1000.0, le=1000.0, description="floor height (default: the lowest floor)")]
CellM = Annotated[float, Query(ge=0.01, le=1.0, description="map resolution, metres per pixel")]


def _nav2(map_id: str, bus: TypedBus, settings: GatewaySettings, version: int | None, floor_z_m: float | None,
          cell_m: float) -> tuple[dict[str, bytes], str]:
    xyz, _, v = ask(f"map {map_id!r}", lambda: map_cloud(bus, settings, map_id, version))
    try:
        grid = occupancy_from_cloud(xyz, floor_z_m, OccupancyConfig(cell_m=cell_m))
    except EmptyMapError as exc:
        raise GatewayError(f"map {map_id!r}: {exc}", 409) from None
    except ValueError as exc:
        raise GatewayError(f"map {map_id!r}: {exc}", 422) from None
    stem = f"{map_id}-v{v}"
    return nav2_files(grid, stem), stem


@router.get("/maps/{map_id}/nav2.yaml", response_class=Response, responses={200: {"content": {"text/yaml": {}}},
                                                                              404: {}, 409: {}, 503: {}})
def map_nav2_yaml(map_id: MapId, bus: BusDep, settings: SettingsDep, version: Version = None,
                  floor_z_m: FloorZ = None, cell_m: CellM = 0.05) -> Response:
    """The map_server YAML (image, mode, resolution, origin, negate, thresholds); its ``image`` names the
    PGM of ``nav2.pgm`` by the file name that route downloads as."""
    files, stem = _nav2(map_id, bus, settings, version, floor_z_m, cell_m)
    return Response(files[f"{stem}.yaml"], media_type="text/yaml",
                    headers={"Content-Disposition": f'attachment; filename="{stem}.yaml"'})


@router.get("/maps/{map_id}/nav2.pgm", response_class=Response,
            responses={200: {"content": {"image/x-portable-graymap": {}}}, 404: {}, 409: {}, 503: {}})
def map_nav2_pgm(map_id: MapId, bus: BusDep, settings: SettingsDep, version: Version = None,
                 floor_z_m: FloorZ = None, cell_m: CellM = 0.05) -> Response:
    """The occupancy image (binary PGM: 0 occupied, 254 free, 205 unknown)."""
    files, stem = _nav2(map_id, bus, settings, version, floor_z_m, cell_m)
    return Response(files[f"{stem}.pgm"], media_type="image/x-portable-graymap",
                    headers={"Content-Disposition": f'attachment; filename="{stem}.pgm"'})


@router.get("/maps/{map_id}/nav2.zip", response_class=Response,
            responses={200: {"content": {"application/zip": {}}}, 404: {}, 409: {}, 503: {}})
def map_nav2_zip(map_id: MapId, bus: BusDep, settings: SettingsDep, version: Version = None,
                 floor_z_m: FloorZ = None, cell_m: CellM = 0.05) -> Response:
    """Both Nav2 files in one zip: ``ros2 run nav2_map_server map_server --ros-args -p yaml_filename:=...``."""
    files, stem = _nav2(map_id, bus, settings, version, floor_z_m, cell_m)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in files.items():
            z.writestr(name, data)
    return Response(buf.getvalue(), media_type="application/zip",
                    headers={"Content-Disposition": f'attachment; filename="{stem}-nav2.zip"'})

