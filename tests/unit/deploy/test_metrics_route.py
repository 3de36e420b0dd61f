"""GET /metrics: every instance's ServiceMetrics from the bus, in Prometheus text format."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from services.gateway.app import create_app
from services.gateway.routes.metrics import prometheus_text
from services.gateway.settings import GatewaySettings
from shared import keys
from shared.bus import FakeBus, FakeNetwork
from shared.bus.base import QueryFailed
from shared.runner import RunningService, Service, ServiceSettings
from shared.schemas import EndpointStats, MoveRequest, PoseReply, Pose, ServiceMetrics

SAMPLE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{[^}]*\})? (-?[0-9.e+-]+)$')


class Echo(Service):
    name = "renderer"

    def start(self, node):
        def handle(req: MoveRequest) -> PoseReply:
            if req.dx_m < 0:
                raise ValueError("backwards")
            return PoseReply(pose=Pose(position_m=(req.dx_m, req.dy_m, 0)))

        node.serve("ant/render/views", MoveRequest, handle, replicated=True)


def parse(text: str) -> dict[tuple[str, frozenset], float]:
    out = {}
    for line in text.splitlines():
        if line.startswith("#") or not line:
            continue
        m = SAMPLE.match(line)
        assert m, f"not a Prometheus sample line: {line!r}"
        labels = frozenset(re.findall(r'(\w+)="((?:[^"\\]|\\.)*)"', m.group(2) or ""))
        out[(m.group(1), labels)] = float(m.group(3))
    return out


@pytest.fixture
def net():
    return FakeNetwork()


def test_metrics_aggregates_every_instance(net, tmp_path):
    buses = [FakeBus(net) for _ in range(2)]
    svcs = [RunningService(Echo(ServiceSettings(instance=f"r{i}")), b) for i, b in enumerate(buses)]
    try:
        from shared.bus.typed import RemoteError, TypedBus
        client = TypedBus(FakeBus(net), "test")
        for i in range(7):
            client.request("ant/render/views", MoveRequest(dx_m=i, dy_m=0), PoseReply, balance="renderer")
        with pytest.raises(RemoteError):
            client.request(keys.routed("ant/render/views", "r1"), MoveRequest(dx_m=-1, dy_m=0), PoseReply)
        settings = GatewaySettings(instance="gw-test", db_path=tmp_path / "gw.sqlite3", status_timeout_s=1.0)
        app = create_app(settings, bus_factory=lambda _s: FakeBus(net))
        with TestClient(app) as http:
            resp = http.get("/metrics")
        assert resp.status_code == 200
        assert resp.headers["content-type"].startswith("text/plain; version=0.0.4")
        samples = parse(resp.text)
    finally:
        for s in svcs:
            s.close()

    def value(name, **labels):
        return samples[(name, frozenset(labels.items()))]

    # both replicas, and the gateway itself, report; requests were balanced 4/3 and the error counted
    for inst in ("r0", "r1"):
        assert value("ant_up", service="renderer", instance=inst) == 1
    assert value("ant_up", service="gateway", instance="gw-test") == 1
    reqs = [value("ant_requests_total", service="renderer", instance=i, endpoint="views") for i in ("r0", "r1")]
    assert sum(reqs) == 8 and min(reqs) >= 3
    assert value("ant_errors_total", service="renderer", instance="r1", endpoint="views") == 1
    assert value("ant_errors_total", service="renderer", instance="r0", endpoint="views") == 0
    p50 = value("ant_latency_p50_seconds", service="renderer", instance="r0", endpoint="views")
    p99 = value("ant_latency_p99_seconds", service="renderer", instance="r0", endpoint="views")
    assert 0 < p50 <= p99 < 1.0
    assert ("ant_queue_depth", frozenset({"service": "renderer", "instance": "r0", "endpoint": "views"}.items())) \
        in samples
    assert value("ant_uptime_seconds", service="renderer", instance="r0") >= 0
    assert value("ant_metrics_scrape_errors") == 0


def test_an_instance_that_fails_its_metrics_query_is_counted_not_fatal(net, tmp_path):
    bad = FakeBus(net)

    def broken(_key, _payload):
        raise QueryFailed(b"metrics unavailable")

    bad.serve(keys.METRICS.format(service="planner", instance="p0"), broken)
    settings = GatewaySettings(instance="gw-test", db_path=tmp_path / "gw.sqlite3")
    app = create_app(settings, bus_factory=lambda _s: FakeBus(net))
    with TestClient(app) as http:
        samples = parse(http.get("/metrics").text)
    bad.close()
    assert samples[("ant_metrics_scrape_errors", frozenset())] == 1
    assert ("ant_up", frozenset({"service": "gateway", "instance": "gw-test"}.items())) in samples


def test_text_format_is_valid_and_escapes_labels():
    m = ServiceMetrics(service="renderer", instance='we"ird\\name', uptime_s=12.5,
                       endpoints={"views": EndpointStats(requests=3, errors=1, latency_p50_ms=2.0,
                                                         latency_p99_ms=9.0, queue_depth=4)})
    text = prometheus_text([m], scrape_errors=0, scrape_s=0.01)
    assert text.endswith("\n")
    names_with_type = re.findall(r"^# TYPE (\w+) (counter|gauge)$", text, re.M)
    assert ("ant_requests_total", "counter") in names_with_type and ("ant_queue_depth", "gauge") in names_with_type
    # every sample belongs to a family declared before it
    declared = set()
    for line in text.splitlines():
        if line.startswith("# TYPE"):
            declared.add(line.split()[2])
        elif not line.startswith("#"):
            assert SAMPLE.match(line).group(1) in declared
    samples = parse(text)
    lab = frozenset({"service": "renderer", "instance": 'we\\"ird\\\\name', "endpoint": "views"}.items())
    assert samples[("ant_latency_p99_seconds", lab)] == pytest.approx(0.009)
    assert samples[("ant_queue_depth", lab)] == 4
