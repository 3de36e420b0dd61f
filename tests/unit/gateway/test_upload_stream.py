"""Uploads in parts (issue 15 item 12): POST /maps spools the body and sends it to the real
reconstructor service in parts; every way an upload can fail leaves no map, no partial file on the
reconstructor and nothing in the gateway's spool.

Gateway and reconstructor are the real ones, on one in-process fake network (every message is encoded
and decoded as on zenoh); the measured memory class is tests/reliability/test_upload_memory.py.
"""

from __future__ import annotations

import io
from contextlib import contextmanager

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
        self.spool = tmp_path / "spool"
        self.spool.mkdir()
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
                                   request_timeout_s=10.0, upload_spool_dir=self.spool, **overrides)
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
    assert store.staged == [] and list(store.spool.iterdir()) == []


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
    assert store.maps() == [] and store.staged == [] and list(store.spool.iterdir()) == []


def test_an_unreadable_upload_in_parts_is_422_and_leaves_nothing(store):
    junk = b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\nproperty float x\nend_header\n"
    junk += b"\1" * (IMPORT_PART_BYTES + 100)
    with store.gateway() as http:
        r = http.post("/maps", params={"map_id": "junk", "filename": "junk.ply"}, content=junk, headers=HEADERS)
        assert r.status_code == 422, r.text
        assert "junk.ply" in r.json()["detail"] and ".part" not in r.json()["detail"]
    assert store.maps() == [] and store.staged == [] and list(store.spool.iterdir()) == []


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
