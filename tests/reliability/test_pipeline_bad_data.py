"""Bad data in the pipeline, each with a clear outcome: non-finite poses (HTTP 422 and bus
``bad_request``, the handler never runs), an empty or tiny cloud (import refused, nothing stored)."""

from __future__ import annotations

import math

import httpx
import numpy as np
import pytest

from services.reconstructor.core.errors import MapStoreError
from services.reconstructor.core.store import MapStore
from services.renderer.core.errors import CloudFormatError
from shared import keys
from shared.bus import FakeBus, FakeNetwork
from shared.bus.base import QueryTarget
from shared.bus.typed import TypedBus
from shared.codec import decode
from shared.schemas import ErrorCode, ErrorReply, MoveRequest, PoseReply, ResetRequest, Pose
from tests.reliability.fuzzing import _envelope
from tests.reliability.http_server import live_gateway

NON_FINITE = [math.nan, math.inf, -math.inf]


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_start_pose_over_http_is_422(tmp_path, literal):
    body = ('{"instruction": "go", "map_id": "house", "options": {"start_pose": '
            f'{{"position_m": [1.0, {literal}, 0.0], "heading_rad": 0.0}}}}}}')
    with live_gateway(tmp_path) as (url, _world), httpx.Client(base_url=url, timeout=10) as http:
        r = http.post("/missions", content=body, headers={"Content-Type": "application/json"})
        assert r.status_code == 422, r.text
        assert http.get("/missions").json()["total"] == 0


@pytest.mark.parametrize("value", NON_FINITE)
@pytest.mark.parametrize("make", [
    lambda v: ("MoveRequest", {"dx_m": v, "dy_m": 0.0}, keys.IO_MOVE),
    lambda v: ("ResetRequest", {"pose": {"position_m": [0.0, v, 0.0], "heading_rad": 0.0}}, keys.IO_RESET),
    lambda v: ("ResetRequest", {"pose": {"position_m": [0.0, 0.0, 0.0], "heading_rad": v}}, keys.IO_RESET),
])
def test_non_finite_pose_on_the_bus_is_bad_request_and_never_reaches_the_robot(value, make):
    schema, data, key_t = make(value)
    model = {"MoveRequest": MoveRequest, "ResetRequest": ResetRequest}[schema]
    net = FakeNetwork()
    served, asker = FakeBus(net), FakeBus(net)
    calls = []
    key = key_t.format(robot="robot0")
    TypedBus(served, "robot_io").serve(key, model, lambda req: calls.append(req) or PoseReply(pose=Pose(position_m=(0, 0, 0))))
    replies = asker.query(key, _envelope({"s": schema, "v": 1, "d": data, "a": []}), timeout_s=2.0,
                          target=QueryTarget.BEST)
    assert replies and not replies[0].ok
    err = decode(replies[0].error, ErrorReply)
    assert err.code == ErrorCode.BAD_REQUEST and "finite" in err.message
    assert not calls
    served.close()
    asker.close()


def _ply(n: int) -> bytes:
    pts = np.random.default_rng(0).uniform(-1, 1, (n, 3)).astype("<f4")
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n" \
           "property float z\nend_header\n"
    return head.encode() + pts.tobytes()


@pytest.mark.parametrize("data", [_ply(0), b"ply\nformat ascii 1.0\nend_header\n", b"ply\ngarbage",
                                  b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
                                  b"property float y\nproperty float z\nend_header\n" + b"\0" * 12])
def test_empty_tiny_or_broken_cloud_import_is_refused_and_stores_nothing(tmp_path, data):
    store = MapStore(tmp_path / "maps", fsync=False)
    with pytest.raises((MapStoreError, CloudFormatError)) as info:
        store.import_cloud("bad", data, filename="bad.ply")
    assert str(info.value)
    assert store.list() == []
    assert not [p for p in (tmp_path / "maps").rglob("*") if p.is_file() and p.name != ".lock"]
