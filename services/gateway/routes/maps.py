"""Maps: list, metadata, download the cloud as PLY (streamed), upload a PLY/PCD cloud."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Annotated

import anyio.from_thread
import numpy as np
from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from services.gateway.deps import Authorized, BusDep, SettingsDep
from services.gateway.errors import GatewayError, ask
from services.gateway.params import SEGMENT, MapId, Version
from shared import cloud as ply
from shared.clients import MapClient
from shared.schemas import ErrorCode, MapInfo, SceneGraph

log = logging.getLogger(__name__)
router = APIRouter(prefix="/maps", tags=["maps"])
_HEAD_BYTES = 256  # enough of the body to tell a PLY from a PCD


class _BodyReader:
    """The request body as a blocking binary file for a worker thread: ``read(n)`` pulls the body's
    chunks from the event loop (``anyio.from_thread``) until it has ``n`` bytes or the body ends. It
    refuses, before the first part leaves, a body that is not the file its name says, and, whenever it
    happens, a body over ``max_bytes``; a client that goes away surfaces as the stream's error. Any of
    these raised inside ``MapClient.import_cloud`` aborts the upload on the reconstructor."""

    def __init__(self, request: Request, max_bytes: int, filename: str):
        self._chunks = request.stream().__aiter__()
        self._buf = bytearray()
        self._ended = False
        self._checked = False
        self.max_bytes, self.filename, self.size = max_bytes, filename, 0

    async def _next(self) -> bytes | None:
        try:
            return await self._chunks.__anext__()
        except StopAsyncIteration:
            return None

    def read(self, n: int) -> bytes:
        while len(self._buf) < n and not self._ended:
            chunk = anyio.from_thread.run(self._next)
            if chunk is None:
                self._ended = True
                break
            self.size += len(chunk)
            if self.size > self.max_bytes:
                raise GatewayError(f"request body larger than {self.max_bytes} bytes", 413,
                                   code=ErrorCode.BUDGET_EXCEEDED.value)
            self._buf += chunk
            if not self._checked and len(self._buf) >= _HEAD_BYTES:
                self._check_head()
        if not self._checked:
            self._check_head()
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def _check_head(self) -> None:
        self._checked = True
        if not self._buf:
            raise GatewayError("empty body: send the PLY/PCD file as the request body", 422)
        head = bytes(self._buf[:_HEAD_BYTES]).lstrip()
        is_ply = head.startswith(b"ply")
        is_pcd = head.startswith(b"#") or head.startswith(b"VERSION")
        name = self.filename
        if not (is_ply and name.endswith(".ply")) and not (is_pcd and name.endswith(".pcd")):
            raise GatewayError(f"{name!r}: the body is not a {name.rsplit('.', 1)[-1].upper()} file", 415)


@router.get("", response_model=list[MapInfo], responses={503: {}})
def list_maps(bus: BusDep, settings: SettingsDep) -> list[MapInfo]:
    """Every stored map (latest versions), as the reconstructor reports them."""
    return ask("cannot list maps", lambda: MapClient(bus, timeout_s=settings.request_timeout_s).list())


@router.get("/{map_id}", response_model=MapInfo, responses={404: {}, 503: {}})
def get_map(map_id: MapId, bus: BusDep, settings: SettingsDep, version: Version = None) -> MapInfo:
    """Metadata of one map: points, bounds, labels, regions, metric scale factors, timings."""
    return ask(f"map {map_id!r}", lambda: MapClient(bus, timeout_s=settings.request_timeout_s).info(map_id, version))


@router.get("/{map_id}/scene-graph.json", response_model=SceneGraph, responses={404: {}, 503: {}})
def get_scene_graph(map_id: MapId, bus: BusDep, settings: SettingsDep, version: Version = None) -> SceneGraph:
    """The map version's scene graph: rooms (type, floor, footprint, area, neighbours), openings, objects
    (class, dominant colour, position, size, room), stairs, the exploration's navigation graph and each
    floor's walkable cells. Built from what the robot recorded, never from a simulator's scene."""
    return ask(f"scene graph of map {map_id!r}",
               lambda: MapClient(bus, timeout_s=settings.request_timeout_s).scene_graph(map_id, version))


@router.get("/{map_id}/cloud.ply", response_class=StreamingResponse,
            responses={200: {"content": {"application/octet-stream": {}}, "description": "binary PLY"},
                       404: {}, 503: {}})
def download_cloud(map_id: MapId, bus: BusDep, settings: SettingsDep, version: Version = None) -> StreamingResponse:
    """The map's points as a binary little-endian PLY (x y z float, red green blue uchar[, label int]
    [, view_x view_y view_z char: where each point was seen from]), streamed chunk by chunk so a large
    cloud never sits whole in the gateway's memory. Uploaded again, it renders as the original does."""
    info = get_map(map_id, bus, settings, version)
    # The first chunk before the response starts: an error is still a clean status code, and it
    # tells whether the cloud has labels; the client pins later chunks to its version.
    chunks = MapClient(bus, timeout_s=settings.request_timeout_s).chunks(map_id, info.version,
                                                                          settings.map_chunk_points)
    first = ask(f"map {map_id!r}", lambda: next(chunks))
    with_labels = first.labels is not None
    with_views = first.view_dirs is not None
    header = ply.header(info.point_count, with_labels, info.label_names, f"SpatialAnt map {map_id} version {first.version}",
                        with_views=with_views)
    size = len(header) + info.point_count * ply.vertex_dtype(with_labels, with_views).itemsize

    def records(c) -> bytes:
        # Every chunk of one version comes from one stored cloud; zeros (no side known) would keep
        # the layout should one chunk lack the views the first had.
        views = (c.view_dirs if c.view_dirs is not None else np.zeros((len(c.xyz_m), 3), np.int8)) if with_views else None
        return ply.records(c.xyz_m, c.rgb, c.labels, with_labels, view_dirs=views)

    def body() -> Iterator[bytes]:
        yield header
        sent = len(first.xyz_m)
        yield records(first)
        for c in chunks:  # an error here ends the stream short of Content-Length
            sent += len(c.xyz_m)
            yield records(c)
        if sent != info.point_count:
            log.error("map %s v%d: chunks held %d points, info said %d", map_id, first.version, sent,
                      info.point_count)

    filename = f"{map_id}-v{first.version}.ply"
    return StreamingResponse(body(), media_type="application/octet-stream",
                             headers={"Content-Length": str(size),
                                      "Content-Disposition": f'attachment; filename="{filename}"'})


@router.post("", response_model=MapInfo, status_code=status.HTTP_201_CREATED, dependencies=[Authorized],
             responses={401: {}, 413: {}, 415: {}, 422: {}, 503: {}},
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
async def upload_cloud(request: Request, bus: BusDep, settings: SettingsDep, response: Response,
                       map_id: Annotated[str, Query(pattern=SEGMENT, description="name of the new map")],
                       filename: Annotated[str, Query(pattern=r"^[^/\\\x00-\x1f]{1,200}\.(ply|pcd)$")] = "cloud.ply",
                       ) -> MapInfo:
    """Store a PLY or PCD cloud as a map: the file is the raw body
    (``curl --data-binary @room.ply -H 'Content-Type: application/octet-stream' '/maps?map_id=room'``).

    The body is streamed to the reconstructor in parts as it arrives (``MapClient.import_cloud`` reads
    it from :class:`_BodyReader`): the gateway holds a part or two, never the file, and writes nothing
    to disk. A body that is too large, not a cloud, or cut short (the client went away) aborts the
    upload on the reconstructor, which then drops what it had received: nothing is left behind."""
    body = _BodyReader(request, settings.max_upload_bytes, filename)
    # Blocking bus requests: off the event loop; the reader hops back onto it for each body chunk.
    info = await run_in_threadpool(ask, f"cannot import {filename!r}", lambda: MapClient(
        bus, timeout_s=settings.request_timeout_s).import_cloud(map_id, filename, body))
    response.headers["Location"] = f"/maps/{map_id}"
    return info
