"""The zenoh adapter honours the Bus contract that the fake bus models."""

import threading

import numpy as np
import pytest

from shared import keys
from shared.bus.base import QueryTarget
from shared.bus.typed import RemoteError, TypedBus
from shared.runner import RunningService, ServiceSettings
from shared.schemas import ErrorCode, MapChunk, MoveRequest, Ping, PoseReply, ServiceInfo
from tests.contract.conftest import wait_until
from tests.unit.shared.test_bus import Echo

pytestmark = pytest.mark.contract


def test_publish_subscribe_in_order(peers):
    a, b = peers
    got = []
    b.subscribe("ant/t/**", lambda k, d: got.append((k, d)))
    # Ready when a probe sample arrives (the subscription has propagated to the other peer).
    wait_until(lambda: a.publish("ant/t/probe", b"p") or any(k == "ant/t/probe" for k, _ in got), what="sub")
    for i in range(100):
        a.publish("ant/t/x", i.to_bytes(2, "little"))
    xs = lambda: [int.from_bytes(d, "little") for k, d in got if k == "ant/t/x"]  # noqa: E731
    wait_until(lambda: len(xs()) >= 100, what="100 samples")
    assert xs() == list(range(100))


def test_typed_service_over_real_zenoh(peers):
    a, b = peers
    with RunningService(Echo(ServiceSettings(instance="z1")), a):
        client = TypedBus(b)
        wait_until(lambda: client.raw.alive(keys.ALIVE.format(service="echo", instance="z1")), what="alive")
        key = keys.IO_MOVE.format(robot="robot0")
        assert client.request(key, MoveRequest(dx_m=1.5, dy_m=0), PoseReply).pose.position_m[0] == 1.5
        with pytest.raises(RemoteError) as e:
            client.request(key, MoveRequest(dx_m=11, dy_m=0), PoseReply)
        assert e.value.code == ErrorCode.NOT_FOUND
        (reply,) = b.query(key, b"\x00garbage")
        assert not reply.ok
        with pytest.raises(RemoteError) as e:
            client._decode_reply(key, reply, PoseReply)
        assert e.value.code == ErrorCode.BAD_REQUEST
        infos = client.request_all(keys.INFO.pattern(), Ping(), ServiceInfo)
        assert [i.instance for i in infos] == ["z1"]


def test_liveliness_appears_and_disappears(peers):
    a, b = peers
    events = []
    b.watch_liveliness("ant/alive/**", lambda k, alive: events.append((k, alive)))
    tok = a.liveliness_token("ant/alive/svc/i1")
    wait_until(lambda: ("ant/alive/svc/i1", True) in events, what="token seen")
    tok.close()
    wait_until(lambda: ("ant/alive/svc/i1", False) in events, what="token gone")


def test_large_cloud_chunk_crosses_intact(peers):
    a, b = peers
    n = 1_000_000
    rng = np.random.default_rng(1)
    chunk = MapChunk(map_id="m", version=1, index=0, count=1, xyz_m=rng.random((n, 3), dtype=np.float32),
                     rgb=rng.integers(0, 255, (n, 3), dtype=np.uint8))
    ta, tb = TypedBus(a), TypedBus(b)
    got = []
    done = threading.Event()
    tb.subscribe("ant/maps/m/chunk", MapChunk, lambda k, m: (got.append(m), done.set()))
    wait_until(lambda: ta.publish("ant/maps/m/chunk", chunk) or done.wait(0.2), what="chunk delivered")
    assert np.array_equal(got[0].xyz_m, chunk.xyz_m) and np.array_equal(got[0].rgb, chunk.rgb)


def test_all_target_reaches_every_replica(peers):
    a, b = peers
    a.serve("ant/svc/r/a/info", lambda k, p: b"a")
    b.serve("ant/svc/r/b/info", lambda k, p: b"b")
    wait_until(lambda: len(b.query("ant/svc/r/*/info", target=QueryTarget.ALL, timeout_s=1)) == 2, what="both")


def test_cached_events_reach_a_subscriber_that_starts_later(peers):
    a, b = peers
    for i in range(5):
        a.publish("ant/r/missions/m1/events", bytes([i]), cache=100)
    got = []
    b.subscribe("ant/*/missions/*/events", lambda k, d: got.append(d[0]), history=True)
    wait_until(lambda: len(got) >= 5, what="history delivered")
    a.publish("ant/r/missions/m1/events", bytes([5]), cache=100)
    wait_until(lambda: 5 in got, what="live sample")
    assert sorted(set(got)) == list(range(6))
