"""Uploads in parts (issue 15 item 12, issue 31 item 4): POST /maps streams the body to the real
reconstructor service in parts as it arrives (the gateway writes nothing to disk); every way an upload
can fail leaves no map and no partial file on the reconstructor.

Gateway and reconstructor are the real ones, on one in-process fake network (every message is encoded
and decoded as on zenoh); the measured memory class is tests/reliability/test_upload_memory.py.
"""

from __future__ import annotations

import io
from contextlib import contextmanager

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from services.reconstructor.service import ReconstructorService, ReconstructorSettings
from shared import keys
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import RemoteError, TypedBus
from shared.clients import MapClient
from shared.cloud import PointCloud, encode
from shared.runner import RunningService
from tests.waiting import wait_until
from shared.schemas import IMPORT_MAX_BYTES, IMPORT_PART_BYTES, ErrorCode, MapImportProgress, MapImportRequest

HEADERS = {"Content-Type": "application/octet-stream"}


def cloud_ply(points: int, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    return encode(PointCloud(rng.uniform(-5, 5, (points, 3)).astype(np.float32),
                             rng.integers(0, 256, (points, 3), dtype=np.uint8)))


class Store:
    def __init__(self, tmp_path):
        self.net = FakeNetwork()
        self.root = tmp_path / "maps"
        self.bus = FakeBus(self.net)
        self.service = RunningService(ReconstructorService(ReconstructorSettings(
            instance="rec-upload", store_dir=str(self.root))), self.bus)
        self.client_bus = FakeBus(self.net)
        self.typed = TypedBus(self.client_bus, "upload-test")
        self.tmp_path = tmp_path

    @property
    def staged(self) -> list[str]:
        return sorted(p.name for p in (self.root / ".uploads").iterdir())

    def maps(self) -> list[str]:
        return sorted(p.name for p in self.root.iterdir() if not p.name.startswith("."))

    @contextmanager
    def gateway(self, **overrides):
        settings = GatewaySettings(instance="gw-upload", db_path=self.tmp_path / "gw.sqlite3",
                                   request_timeout_s=10.0, **overrides)
        with TestClient(create_app(settings, bus_factory=lambda _s: FakeBus(self.net))) as client:
            yield client

    def close(self):
        self.client_bus.close()
        self.service.close()
        self.bus.close()


@pytest.fixture
def store(tmp_path):
    s = Store(tmp_path)
    yield s
    s.close()


def test_an_upload_larger_than_a_part_is_stored_whole(store):
    data = cloud_ply(2 * IMPORT_PART_BYTES // 15 + 1000)  # three parts
    assert len(data) > 2 * IMPORT_PART_BYTES
    with store.gateway() as http:
        r = http.post("/maps", params={"map_id": "big", "filename": "big.ply"}, content=data, headers=HEADERS)
        assert r.status_code == 201, r.text
        assert r.json()["point_count"] == 2 * IMPORT_PART_BYTES // 15 + 1000
        got = http.get("/maps/big/cloud.ply")
    # The stored map is the upload, byte for byte in its records.
    assert got.content.split(b"end_header\n", 1)[1] == data.split(b"end_header\n", 1)[1]
    assert store.staged == []


def test_a_body_over_the_limit_is_413_and_leaves_nothing(store):
    def body():  # chunked (no Content-Length): the limit is found while streaming
        for _ in range(40):
            yield b"ply\n" + b"\0" * (64 << 10)

    with store.gateway(max_upload_bytes=1 << 20) as http:
        r = http.post("/maps", params={"map_id": "huge", "filename": "huge.ply"}, content=body(), headers=HEADERS)
        assert r.status_code == 413, r.text
        assert r.json()["code"] == "budget_exceeded"
        # A declared length over the limit is refused before a byte is read.
        r = http.post("/maps", params={"map_id": "huge", "filename": "huge.ply"}, content=b"ply\n" * (300 << 10),
                      headers=HEADERS)
        assert r.status_code == 413, r.text
    assert store.maps() == [] and store.staged == []


def test_an_unreadable_upload_in_parts_is_422_and_leaves_nothing(store):
    junk = b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\nproperty float x\nend_header\n"
    junk += b"\1" * (IMPORT_PART_BYTES + 100)
    with store.gateway() as http:
        r = http.post("/maps", params={"map_id": "junk", "filename": "junk.ply"}, content=junk, headers=HEADERS)
        assert r.status_code == 422, r.text
        assert "junk.ply" in r.json()["detail"] and ".part" not in r.json()["detail"]
    assert store.maps() == [] and store.staged == []


def test_a_sender_that_fails_mid_way_aborts_its_upload(store):
    data = cloud_ply(IMPORT_PART_BYTES // 15 * 2)

    class Broken(io.BytesIO):
        reads = 0

        def read(self, n=-1):
            self.reads += 1
            if self.reads == 3:  # after two parts went out (one is read ahead)
                raise OSError("disk gone")
            return super().read(n)

    with pytest.raises(OSError, match="disk gone"):
        MapClient(store.typed, timeout_s=10).import_cloud("half", "half.ply", Broken(data))
    assert store.maps() == [] and store.staged == []


def test_parts_out_of_order_or_of_another_map_drop_the_upload(store):
    key = keys.MAP_IMPORT.format(map="m")
    part = b"ply\n" + b"\0" * 100

    def send(**kw):
        req = MapImportRequest(**{"map_id": "m", "filename": "m.ply", "upload_id": "u1", "last": False, **kw})
        return store.typed.request(key, req, MapImportProgress, timeout_s=5)

    assert send(data=part).received_bytes == len(part)
    with pytest.raises(RemoteError) as e:
        send(data=part, offset=7)  # a gap
    assert e.value.code == ErrorCode.BAD_REQUEST and "offset 7" in e.value.message
    assert store.staged == []  # the whole upload was dropped
    send(data=part)
    with pytest.raises(RemoteError):
        send(data=part, offset=len(part), map_id="other")
    assert store.staged == []
    with pytest.raises(RemoteError) as e:  # over the import budget: refused before any work
        send(data=b"xx", offset=IMPORT_MAX_BYTES - 1)
    assert e.value.code == ErrorCode.BUDGET_EXCEEDED
    assert store.maps() == []



@contextmanager
def live_gateway(store):
    """The gateway served by uvicorn on a free 127.0.0.1 port (a real HTTP server: the TestClient
    reads a request body whole before the app sees it, so it cannot show streaming)."""
    import threading

    import uvicorn

    from deploy.launcher import free_port

    port = free_port()
    settings = GatewaySettings(instance="gw-live", host="127.0.0.1", port=port,
                               db_path=store.tmp_path / "gw-live.sqlite3", request_timeout_s=10.0)
    server = uvicorn.Server(uvicorn.Config(create_app(settings, bus_factory=lambda _s: FakeBus(store.net)),
                                           host="127.0.0.1", port=port, log_config=None,
                                           timeout_graceful_shutdown=1))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"

    def up():
        try:
            return httpx.get(f"{url}/health", timeout=1).status_code == 200
        except httpx.HTTPError:
            return False

    try:
        wait_until(up, what="live gateway up")
        yield url, port
    finally:
        server.should_exit = True
        thread.join(10)


def _chunks(data: bytes, size: int = 1 << 20) -> list[bytes]:
    return [data[i:i + size] for i in range(0, len(data), size)]


def test_the_body_reaches_the_reconstructor_while_it_is_still_arriving(store):
    """Streamed, not spooled: the sender holds back the body's end until a part is staged on the
    reconstructor (a gateway that read the body whole first would never let that happen)."""
    data = cloud_ply(4 * IMPORT_PART_BYTES // 15)
    chunks = _chunks(data)

    def body():
        yield from chunks[:-1]
        wait_until(lambda: store.staged, what="a part staged on the reconstructor before the body ended")
        yield chunks[-1]

    with live_gateway(store) as (url, _port):
        r = httpx.post(f"{url}/maps", params={"map_id": "live", "filename": "live.ply"}, content=body(),
                       headers=HEADERS, timeout=60)
        assert r.status_code == 201, r.text
        assert r.json()["point_count"] == 4 * IMPORT_PART_BYTES // 15
    assert store.maps() == ["live"] and store.staged == []


def test_a_client_that_goes_away_mid_body_leaves_nothing(store):
    """The connection closes mid-body after the reconstructor has parts of it: it drops them all."""
    import socket

    data = cloud_ply(4 * IMPORT_PART_BYTES // 15)
    with live_gateway(store) as (_url, port):
        with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
            sock.sendall(f"POST /maps?map_id=gone&filename=gone.ply HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                         f"Content-Type: application/octet-stream\r\nContent-Length: {len(data)}\r\n\r\n".encode())
            sock.sendall(data[:3 * IMPORT_PART_BYTES])
            wait_until(lambda: store.staged, what="parts staged before the client goes away")
        wait_until(lambda: not store.staged, what="the broken upload dropped")
    assert store.maps() == [] and store.staged == []
