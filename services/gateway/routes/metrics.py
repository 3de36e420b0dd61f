"""``GET /metrics``: every service instance's counters and latencies in Prometheus text format.

Each instance serves its :class:`~shared.schemas.ServiceMetrics` on ``ant/svc/<service>/<instance>/metrics``;
one query on the wildcard collects them all (replicas and other hosts included, whatever is alive).
Counters are cumulative per instance since it started, as Prometheus expects (``rate()`` handles
restarts); latency percentiles are over each endpoint's recent window, hence gauges.
"""

from __future__ import annotations

import time
from collections.abc import Iterable

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from services.gateway.deps import BusDep, SettingsDep
from shared.clients import ServicesClient
from shared.schemas import ServiceMetrics

router = APIRouter(tags=["metrics"])

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

# name -> (type, help); the order of this table is the order of the output.
FAMILIES: dict[str, tuple[str, str]] = {
    "ant_up": ("gauge", "1 for every service instance that answered the metrics query"),
    "ant_uptime_seconds": ("gauge", "seconds since the instance started"),
    "ant_requests_total": ("counter", "requests handled by an endpoint (queries served, samples received)"),
    "ant_errors_total": ("counter", "requests that ended in an error reply"),
    "ant_latency_p50_seconds": ("gauge", "median handling latency over the endpoint's recent window"),
    "ant_latency_p99_seconds": ("gauge", "99th percentile handling latency over the recent window"),
    "ant_queue_depth": ("gauge", "requests waiting for a worker"),
    "ant_metrics_scrape_errors": ("gauge", "instances that answered the metrics query with an error"),
    "ant_metrics_scrape_seconds": ("gauge", "time the gateway took to collect every instance's metrics"),
}


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _labels(**labels: str) -> str:
    return "{" + ",".join(f'{k}="{_escape(v)}"' for k, v in labels.items()) + "}"


def _num(v: float) -> str:
    return repr(int(v)) if float(v).is_integer() and abs(v) < 2**53 else repr(float(v))


def prometheus_text(metrics: Iterable[ServiceMetrics], scrape_errors: int = 0, scrape_s: float = 0.0) -> str:
    """The exposition text for these snapshots (sorted by service, instance, endpoint: stable diffs)."""
    samples: dict[str, list[str]] = {name: [] for name in FAMILIES}
    for m in sorted(metrics, key=lambda m: (m.service, m.instance)):
        inst = {"service": m.service, "instance": m.instance}
        samples["ant_up"].append(f"ant_up{_labels(**inst)} 1")
        samples["ant_uptime_seconds"].append(f"ant_uptime_seconds{_labels(**inst)} {_num(round(m.uptime_s, 3))}")
        for ep_name, ep in sorted(m.endpoints.items()):
            lab = _labels(**inst, endpoint=ep_name)
            samples["ant_requests_total"].append(f"ant_requests_total{lab} {ep.requests}")
            samples["ant_errors_total"].append(f"ant_errors_total{lab} {ep.errors}")
            samples["ant_latency_p50_seconds"].append(f"ant_latency_p50_seconds{lab} {_num(ep.latency_p50_ms / 1e3)}")
            samples["ant_latency_p99_seconds"].append(f"ant_latency_p99_seconds{lab} {_num(ep.latency_p99_ms / 1e3)}")
            samples["ant_queue_depth"].append(f"ant_queue_depth{lab} {ep.queue_depth}")
    samples["ant_metrics_scrape_errors"].append(f"ant_metrics_scrape_errors {scrape_errors}")
    samples["ant_metrics_scrape_seconds"].append(f"ant_metrics_scrape_seconds {_num(round(scrape_s, 6))}")
    lines: list[str] = []
    for name, (kind, help_) in FAMILIES.items():
        lines += [f"# HELP {name} {help_}", f"# TYPE {name} {kind}", *samples[name]]
    return "\n".join(lines) + "\n"


@router.get("/metrics", response_class=PlainTextResponse,
            responses={200: {"content": {CONTENT_TYPE: {}}, "description": "Prometheus text format 0.0.4"}})
def metrics(bus: BusDep, settings: SettingsDep) -> PlainTextResponse:
    """Counters (requests, errors), latency p50/p99, queue depth, up and uptime of every instance on the bus.

    A sync route: the bus query blocks, so FastAPI runs it in its thread pool.
    """
    t0 = time.perf_counter()
    good, errors = ServicesClient(bus, timeout_s=settings.status_timeout_s).metrics()
    text = prometheus_text(good, scrape_errors=errors, scrape_s=time.perf_counter() - t0)
    return PlainTextResponse(text, media_type=CONTENT_TYPE)
