"""The fake bus and the typed layer: the same semantics services rely on over zenoh."""

import threading
import time

import pytest

from shared import keys
from shared.bus import FakeBus, FakeNetwork, QueryTarget
from shared.bus.typed import NoReplyError, NotFound, RemoteError, TypedBus
from shared.codec import encode
from shared.runner import Node, RunningService, Service, ServiceSettings
from tests.waiting import wait_until
from shared.schemas import ErrorCode, MoveRequest, Ping, Pose, PoseReply, ServiceInfo, ServiceMetrics




def test_pub_sub_wildcards_and_order():
    net = FakeNetwork()
    a, b = FakeBus(net), FakeBus(net)
    got = []
    b.subscribe("ant/*/io/pose", lambda k, d: got.append((k, d)))
    for i in range(50):
        a.publish("ant/r1/io/pose", bytes([i]))
    a.publish("ant/r1/io/other", b"x")
    assert wait_until(lambda: len(got) == 50)
    assert [d[0] for _, d in got] == list(range(50))


def test_query_best_and_all_and_timeout():
    net = FakeNetwork()
    a, b, c = FakeBus(net), FakeBus(net), FakeBus(net)
    a.serve("svc/a/info", lambda k, p: b"a")
    b.serve("svc/b/info", lambda k, p: b"b")
    assert sorted(r.payload for r in c.query("svc/*/info", target=QueryTarget.ALL)) == [b"a", b"b"]
    assert len(c.query("svc/*/info")) == 1
    assert c.query("nothing/here", timeout_s=0.1) == []
    release = threading.Event()
    a.serve("slow", lambda k, p: release.wait(2) and b"late")
    assert c.query("slow", timeout_s=0.1) == []
    release.set()


def test_overloaded_queryable_answers_an_error_instead_of_queueing_forever():
    bus = FakeBus()
    gate = threading.Event()
    bus.serve("busy", lambda k, p: gate.wait(2) and b"ok", workers=1, max_queue=1)
    results = []
    threads = [threading.Thread(target=lambda: results.append(bus.query("busy", b"", timeout_s=3)))
               for _ in range(4)]
    for t in threads:
        t.start()
    time.sleep(0.2)
    gate.set()
    for t in threads:
        t.join()
    replies = [r[0] for r in results]
    assert any(not r.ok and b"already queued" in r.error for r in replies)
    assert any(r.ok for r in replies)


def test_liveliness_tokens_and_watch():
    net = FakeNetwork()
    a, b = FakeBus(net), FakeBus(net)
    events = []
    b.watch_liveliness("ant/alive/**", lambda k, alive: events.append((k, alive)))
    tok = a.liveliness_token("ant/alive/x/1")
    assert b.alive("ant/alive/*/*") == ["ant/alive/x/1"]
    tok.close()
    assert b.alive("ant/alive/*/*") == []
    assert events == [("ant/alive/x/1", True), ("ant/alive/x/1", False)]


def test_closing_a_bus_undeclares_everything():
    net = FakeNetwork()
    a, b = FakeBus(net), FakeBus(net)
    a.serve("q", lambda k, p: b"x")
    a.liveliness_token("ant/alive/a/1")
    a.close()
    assert b.query("q", timeout_s=0.1) == [] and b.alive("ant/alive/**") == []


class Echo(Service):
    name = "echo"

    def start(self, node: Node) -> None:
        def move(req: MoveRequest) -> PoseReply:
            if req.dx_m > 10:
                raise NotFound("nothing that far")
            if req.dx_m < -10:
                raise RuntimeError("boom")
            return PoseReply(pose=Pose(position_m=(req.dx_m, req.dy_m, 0.0)))

        node.serve(keys.IO_MOVE.format(robot=node.robot), MoveRequest, move)


def test_running_service_info_metrics_and_typed_errors():
    net = FakeNetwork()
    with RunningService(Echo(ServiceSettings(instance="e1")), FakeBus(net)):
        client = TypedBus(FakeBus(net))
        key = keys.IO_MOVE.format(robot="robot0")
        assert client.request(key, MoveRequest(dx_m=1, dy_m=2), PoseReply).pose.position_m == (1, 2, 0)
        with pytest.raises(RemoteError) as e:
            client.request(key, MoveRequest(dx_m=11, dy_m=0), PoseReply)
        assert e.value.code == ErrorCode.NOT_FOUND and e.value.service == "echo"
        with pytest.raises(RemoteError) as e:
            client.request(key, MoveRequest(dx_m=-11, dy_m=0), PoseReply)
        assert e.value.code == ErrorCode.INTERNAL and "boom" in e.value.message
        # Bad payloads of every kind get a typed BAD_REQUEST and the service keeps serving.
        for bad in [b"", b"garbage", bytes(encode(Ping())), bytes(encode(Pose(position_m=(0, 0, 0))))[:-3]]:
            (reply,) = client.raw.query(key, bad)
            assert not reply.ok
            with pytest.raises(RemoteError) as e:
                client._decode_reply(key, reply, PoseReply)
            assert e.value.code == ErrorCode.BAD_REQUEST
        assert client.request(key, MoveRequest(dx_m=0, dy_m=0), PoseReply)
        info = client.request(keys.INFO.format(service="echo", instance="e1"), Ping(), ServiceInfo)
        assert info.service == "echo" and info.instance == "e1" and info.version
        m = client.request(keys.METRICS.format(service="echo", instance="e1"), Ping(), ServiceMetrics)
        assert m.endpoints["move_to"].requests == 8 and m.endpoints["move_to"].errors == 6
        assert client.raw.alive(keys.ALIVE.pattern()) == ["ant/alive/echo/e1"]
    with pytest.raises(NoReplyError):
        client.request(key, MoveRequest(dx_m=0, dy_m=0), PoseReply, timeout_s=0.1)
    assert client.raw.alive(keys.ALIVE.pattern()) == []


def test_balanced_requests_spread_over_replicas_and_skip_dead_ones():
    net = FakeNetwork()
    served = {"r1": 0, "r2": 0}
    running = []
    for inst in served:
        class Replica(Service):
            name = "renderer"

            def start(self, node: Node, inst=inst) -> None:
                def handle(req: MoveRequest) -> PoseReply:
                    served[inst] += 1
                    return PoseReply(pose=Pose(position_m=(0, 0, 0)))

                node.serve("ant/render/views", MoveRequest, handle, replicated=True)

        running.append(RunningService(Replica(ServiceSettings(instance=inst)), FakeBus(net)))
    client = TypedBus(FakeBus(net))
    for _ in range(20):
        client.request("ant/render/views", MoveRequest(dx_m=0, dy_m=0), PoseReply, balance="renderer")
    assert served == {"r1": 10, "r2": 10}
    running[0].close()  # one replica dies: every request still gets an answer
    for _ in range(10):
        client.request("ant/render/views", MoveRequest(dx_m=0, dy_m=0), PoseReply, balance="renderer")
    assert served == {"r1": 10, "r2": 20}
    running[1].close()
    client.close()


def test_history_subscribers_get_what_publishers_cache():
    net = FakeNetwork()
    pub, late = FakeBus(net), FakeBus(net)
    for i in range(5):
        pub.publish("ant/r/missions/m1/events", bytes([i]), cache=3)
    pub.publish("ant/r/missions/m1/other", b"x")  # not cached
    got = []
    late.subscribe("ant/*/missions/*/events", lambda k, d: got.append(d[0]), history=True)
    pub.publish("ant/r/missions/m1/events", bytes([5]), cache=3)
    assert wait_until(lambda: len(got) == 4)
    assert got == [2, 3, 4, 5]
    pub.release("ant/r/missions/m1/events")
    again = []
    late.subscribe("ant/*/missions/*/events", lambda k, d: again.append(d), history=True)
    time.sleep(0.05)
    assert again == []


def test_metrics_report_the_queue_depth_of_a_busy_endpoint():
    net = FakeNetwork()
    gate = threading.Event()

    class Slow(Service):
        name = "slow"

        def start(self, node: Node) -> None:
            node.serve("ant/slow/q", MoveRequest, lambda r: gate.wait(5) and PoseReply(pose=Pose(position_m=(0, 0, 0))),
                       workers=1)

    with RunningService(Slow(ServiceSettings(instance="s1")), FakeBus(net)):
        client = TypedBus(FakeBus(net))
        payload = bytes(encode(MoveRequest(dx_m=0, dy_m=0)))
        threads = [threading.Thread(target=client.raw.query, args=("ant/slow/q", payload), kwargs={"timeout_s": 6})
                   for _ in range(3)]
        for t in threads:
            t.start()
        assert wait_until(lambda: client.request(keys.METRICS.format(service="slow", instance="s1"), Ping(),
                                                 ServiceMetrics).endpoints["q"].queue_depth == 2)
        gate.set()
        for t in threads:
            t.join()


def test_a_request_that_cannot_be_encoded_is_a_bad_request_not_a_crash():
    from shared.schemas import ExplorationRequest

    client = TypedBus(FakeBus())
    # The schema itself refuses such a number now; built unchecked, it still must not crash the sender.
    with pytest.raises(ValueError):
        ExplorationRequest(exploration_id="x", map_id="m", options={"n": 2**80})
    bad = ExplorationRequest.model_construct(exploration_id="x", map_id="m", options={"n": 2**80})
    with pytest.raises(RemoteError) as e:
        client.request("ant/r/mapper/explorations/submit", bad, PoseReply)
    assert e.value.code == ErrorCode.BAD_REQUEST and "cannot be sent" in e.value.message
