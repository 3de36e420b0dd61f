"""Per-endpoint counters and latencies of one service instance (served on the bus by the runner)."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from shared.schemas import EndpointStats, ServiceMetrics


class _Endpoint:
    __slots__ = ("requests", "errors", "latencies_s", "depth")

    def __init__(self):
        self.requests = 0
        self.errors = 0
        # A bounded window: percentiles describe recent behaviour, memory stays constant.
        self.latencies_s: deque[float] = deque(maxlen=2048)
        self.depth: Callable[[], int] | None = None


class Telemetry:
    def __init__(self, service: str, instance: str):
        self.service, self.instance = service, instance
        self.started = time.time()
        self._lock = threading.Lock()
        self._eps: dict[str, _Endpoint] = {}

    def _ep(self, name: str) -> _Endpoint:
        ep = self._eps.get(name)
        if ep is None:
            with self._lock:
                ep = self._eps.setdefault(name, _Endpoint())
        return ep

    def record(self, endpoint: str, latency_s: float, ok: bool) -> None:
        ep = self._ep(endpoint)
        with self._lock:
            ep.requests += 1
            ep.errors += 0 if ok else 1
            ep.latencies_s.append(latency_s)

    def watch_depth(self, endpoint: str, depth: Callable[[], int]) -> None:
        self._ep(endpoint).depth = depth

    def snapshot(self) -> ServiceMetrics:
        with self._lock:
            eps = {}
            for name, ep in self._eps.items():
                lat = np.asarray(ep.latencies_s) * 1e3
                eps[name] = EndpointStats(
                    requests=ep.requests,
                    errors=ep.errors,
                    latency_p50_ms=float(np.percentile(lat, 50)) if lat.size else 0.0,
                    latency_p99_ms=float(np.percentile(lat, 99)) if lat.size else 0.0,
                    queue_depth=ep.depth() if ep.depth else 0,
                )
        return ServiceMetrics(
            service=self.service, instance=self.instance, uptime_s=time.time() - self.started, endpoints=eps
        )
