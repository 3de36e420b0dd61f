"""bench/replicas: render requests per second with 1 and 2 renderer processes, and the cost of the router hop.

    python -m bench.replicas [--requests 120] [--concurrency 4] [--views 4] [--px 128]

* throughput: a real router + N renderer processes (deploy.launcher), the scripted map store in this
  process, ``--concurrency`` balanced requests in flight; requests/s and the 2-vs-1 ratio. Both
  instances share this machine's cores, so the ratio is bounded by the cores (near 1 on 2 cores).
* router hop: one renderer; the same request from a *peer* (zenoh opens a direct link to the
  renderer, gossip) and from a *client* (every message goes through the router), sequential,
  p50/p99. Also the tiny ``info`` query, where the hop is all there is.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.common import percentiles_ms, table
from deploy.launcher import Launcher
from tests.doubles.scripted_services import ScriptedReconstructor
from shared import keys
from shared.bus.config import ZenohSettings
from shared.bus.typed import TypedBus
from shared.bus.zenoh_bus import ZenohBus
from shared.schemas import (
    CameraIntrinsics, Ping, RenderRequest, RenderResult, ServiceInfo, ServiceMetrics, ViewPose,
)

MAP_POINTS = 200_000


def request(i: int, views: int, px: int) -> RenderRequest:
    h0 = 2 * math.pi * (i % 97) / 97
    return RenderRequest(map_id="bench", camera=CameraIntrinsics(width_px=px, height_px=px),
                         views=[ViewPose(position_m=(0.5, -0.5, 0.0), heading_rad=h0 + k * math.pi / 6)
                                for k in range(views)], with_labels=True)


def throughput(renderers: int, n: int, concurrency: int, views: int, px: int) -> tuple[float, dict[str, int]]:
    with tempfile.TemporaryDirectory() as tmp, \
            Launcher(Path(tmp), replicas={"renderer": renderers}, services=["renderer"], restart=False) as launcher:
        with ZenohBus(launcher.client_settings("reconstructor")) as bus:
            maps = ScriptedReconstructor(TypedBus(bus, "reconstructor"))
            maps.add_random("bench", MAP_POINTS, seed=1, labels=True)
            client = TypedBus(bus, "bench")
            try:
                def one(i):
                    return client.request(keys.RENDER_VIEWS.format(), request(i, views, px), RenderResult,
                                          timeout_s=60, balance="renderer")

                # every instance indexes the map (and warms its caches) before the clock starts
                with ThreadPoolExecutor(renderers * 2) as pool:
                    list(pool.map(one, range(renderers * 4)))
                t0 = time.perf_counter()
                with ThreadPoolExecutor(concurrency) as pool:
                    results = list(pool.map(one, range(n)))
                rate = len(results) / (time.perf_counter() - t0)
                served = {}
                for m in client.request_all(keys.METRICS.pattern(service="renderer"), Ping(), ServiceMetrics):
                    if isinstance(m, ServiceMetrics):
                        served[m.instance] = m.endpoints["views"].requests
                return rate, served
            finally:
                client.close()
                maps.close()


def hop_latency(n: int, views: int, px: int) -> list[tuple]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp, \
            Launcher(Path(tmp), services=["renderer"], restart=False, auth=False) as launcher:
        # Unauthenticated: this compares a peer session with a client one, which the ACL router refuses.
        with ZenohBus(launcher.client_settings()) as source:
            maps = ScriptedReconstructor(TypedBus(source, "reconstructor"))
            maps.add_random("bench", MAP_POINTS, seed=1, labels=True)
            instance = "renderer-0"  # the launcher names replicas <service>-<i>
            info_key = keys.INFO.format(service="renderer", instance=instance)
            views_key = keys.routed(keys.RENDER_VIEWS.format(), instance)
            req = request(0, views, px)
            # Both sessions open at once and requests alternate between them, so that load from
            # elsewhere on the machine (and the renderer's own warm-up) hits both modes alike.
            with ZenohBus(ZenohSettings(mode="peer", connect=[launcher.endpoint])) as peer, \
                    ZenohBus(ZenohSettings(mode="client", connect=[launcher.endpoint])) as client_bus:
                sessions = {"peer": (peer, TypedBus(peer, "bench")), "client": (client_bus, TypedBus(client_bus, "bench"))}
                # a peer learns the renderer's locator by gossip and links to it directly
                deadline = time.monotonic() + 5
                while len(list(peer.session.info.peers_zid())) < 2 and time.monotonic() < deadline:
                    time.sleep(0.05)
                for what, key, msg, model in (("info (tiny)", info_key, Ping(), ServiceInfo),
                                              (f"render {views}x{px}px", views_key, req, RenderResult)):
                    samples = {mode: [] for mode in sessions}
                    for i in range(n + 10):
                        for mode, (_, typed) in sessions.items():
                            t0 = time.perf_counter()
                            typed.request(key, msg, model, timeout_s=30)
                            if i >= 10:  # the first ones warm both paths up
                                samples[mode].append(time.perf_counter() - t0)
                    for mode, (raw, _) in sessions.items():
                        p = percentiles_ms(samples[mode], (50, 99))
                        rows.append((what, mode, len(list(raw.session.info.peers_zid())), p["p50"], p["p99"]))
                for _, typed in sessions.values():
                    typed.close()
            maps.close()
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=120)
    ap.add_argument("--concurrency", type=int, default=4)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--px", type=int, default=128)
    ap.add_argument("--latency-requests", type=int, default=200)
    args = ap.parse_args(argv)
    print(f"machine: {os.cpu_count()} cores; map {MAP_POINTS} points; {args.views} views of {args.px}x{args.px} px "
          f"per request; {args.concurrency} in flight")
    rates = {}
    rows = []
    for n in (1, 2):
        rates[n], served = throughput(n, args.requests, args.concurrency, args.views, args.px)
        rows.append((n, rates[n], " ".join(f"{k}={v}" for k, v in sorted(served.items()))))
    table("Render throughput by renderer replicas", rows, ("renderers", "requests/s", "requests served per instance"))
    ratio = rates[2] / rates[1]
    print(f"\nratio 2/1 = {ratio:.2f}" + (" (expected near 1: both replicas share the same "
                                          f"{os.cpu_count()} cores)" if (os.cpu_count() or 1) <= 2 else ""))
    lat = hop_latency(args.latency_requests, args.views, args.px)
    table("Router hop: same request from a peer (direct link) and from a client (through the router)",
          lat, ("request", "mode", "peers linked", "p50 ms", "p99 ms"))
    by = {(r[0], r[1]): r for r in lat}
    for what in dict.fromkeys(r[0] for r in lat):
        d50 = by[(what, "client")][3] - by[(what, "peer")][3]
        d99 = by[(what, "client")][4] - by[(what, "peer")][4]
        print(f"added by the router hop, {what}: p50 {d50:+.2f} ms, p99 {d99:+.2f} ms")


if __name__ == "__main__":
    main()
