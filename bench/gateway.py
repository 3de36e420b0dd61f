"""Gateway under load: 200 concurrent clients poll ``GET /missions/{id}`` and hold an SSE stream each.

The gateway runs as its own process (``python -m services.gateway``) on 127.0.0.1 over a real zenoh
bus; a scripted planner and reconstructor in this process publish live mission events (with JPEGs)
while the clients hammer it for ``--duration-s`` seconds (30 by default). Loopback only, bounded.
Prints zero-5xx check, request counts and p50/p99 latency.

    python -m bench.gateway [--clients 200] [--duration-s 30]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import httpx

from bench.common import percentiles_ms, table
from deploy.launcher import free_port
from services.gateway.testing import ScriptedPlanner, ScriptedReconstructor
from shared.bus.config import ZenohSettings
from shared.bus.typed import TypedBus

REPO = Path(__file__).resolve().parents[1]


async def _client(http: httpx.AsyncClient, mission_ids: list[str], until: float, lat: list[float],
                  codes: Counter, sse: Counter, rng: random.Random) -> None:
    mid = rng.choice(mission_ids)

    async def hold_stream():
        try:
            async with http.stream("GET", f"/missions/{mid}/events", timeout=httpx.Timeout(5.0, read=None)) as r:
                codes[f"sse {r.status_code}"] += 1
                async for line in r.aiter_lines():
                    if line.startswith("id: "):
                        sse["events"] += 1
                    if time.monotonic() > until:
                        break
        except (httpx.HTTPError, asyncio.CancelledError) as exc:
            if not isinstance(exc, asyncio.CancelledError):
                codes[f"sse error {type(exc).__name__}"] += 1

    stream = asyncio.create_task(hold_stream())
    while time.monotonic() < until:
        t0 = time.perf_counter()
        try:
            r = await http.get(f"/missions/{rng.choice(mission_ids)}")
            codes[r.status_code] += 1
            lat.append(time.perf_counter() - t0)
        except httpx.HTTPError as exc:
            codes[f"error {type(exc).__name__}"] += 1
        await asyncio.sleep(rng.uniform(0.05, 0.25))  # a polling UI, not a tight loop
    stream.cancel()
    await asyncio.gather(stream, return_exceptions=True)


async def _load(url: str, mission_ids: list[str], clients: int, duration_s: float):
    lat: list[float] = []
    codes: Counter = Counter()
    sse: Counter = Counter()
    limits = httpx.Limits(max_connections=2 * clients + 10, max_keepalive_connections=2 * clients)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=30.0) as http:
        until = time.monotonic() + duration_s
        rngs = [random.Random(i) for i in range(clients)]
        await asyncio.gather(*(_client(http, mission_ids, until, lat, codes, sse, r) for r in rngs))
    return lat, codes, sse


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--duration-s", type=float, default=float(os.environ.get("ANT_BENCH_GATEWAY_S", 30)))
    ap.add_argument("--missions", type=int, default=8)
    args = ap.parse_args(argv if argv is not None else [])
    from shared.bus.zenoh_bus import ZenohBus

    zport, hport = free_port(), free_port()
    url = f"http://127.0.0.1:{hport}"
    with tempfile.TemporaryDirectory() as tmp, ZenohBus(ZenohSettings(listen=[f"tcp/127.0.0.1:{zport}"])) as bus:
        typed = TypedBus(bus, "bench")
        recon = ScriptedReconstructor(typed)
        recon.add_random("bench-house", 10_000)
        # Missions that outlive the run, one step a second with ~10 JPEGs: a realistic event rate.
        steps = int(args.duration_s) + 20
        planner = ScriptedPlanner(typed, steps=steps, step_interval_s=1.0, candidates=4, image_px=128)
        env = dict(os.environ, ANT_PORT=str(hport), ANT_HOST="127.0.0.1", ANT_INSTANCE="gateway-bench",
                   ANT_ZENOH__MODE="peer", ANT_ZENOH__CONNECT=f'["tcp/127.0.0.1:{zport}"]',
                   ANT_ZENOH__MULTICAST_SCOUTING="false", ANT_DB_PATH=str(Path(tmp) / "gw.sqlite3"),
                   ANT_LOG_LEVEL="WARNING", PYTHONPATH=str(REPO))
        log = open(Path(tmp) / "gateway.log", "wb")
        proc = subprocess.Popen([sys.executable, "-m", "services.gateway"], env=env, cwd=REPO, stdout=log,
                                stderr=subprocess.STDOUT)
        try:
            end = time.monotonic() + 60
            while True:
                try:
                    if httpx.get(f"{url}/maps", timeout=2).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                if time.monotonic() > end or proc.poll() is not None:
                    raise RuntimeError("the gateway did not come up: " + (Path(tmp) / "gateway.log").read_text()[-2000:])
                time.sleep(0.1)
            ids = []
            for i in range(args.missions):
                r = httpx.post(f"{url}/missions", json={"instruction": f"bench mission {i}", "map_id": "bench-house",
                                                        "options": {"max_steps": 500}}, timeout=10)
                r.raise_for_status()
                ids.append(r.json()["id"])
            t0 = time.perf_counter()
            lat, codes, sse = asyncio.run(_load(url, ids, args.clients, args.duration_s))
            wall = time.perf_counter() - t0
            stored = httpx.get(f"{url}/missions/{ids[0]}", timeout=10).json()["last_seq"] + 1
        finally:
            proc.terminate()
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            log.close()
            planner.close()
            recon.close()
    five_xx = sum(v for k, v in codes.items() if isinstance(k, int) and k >= 500)
    p = percentiles_ms(lat)
    table(f"gateway: {args.clients} clients polling GET /missions/{{id}} + 1 SSE stream each, "
          f"{args.duration_s:.0f} s, {args.missions} live missions",
          [(len(lat), len(lat) / wall, p["p50"], p["p95"], p["p99"], five_xx, sse["events"], stored)],
          ("GET requests", "req/s", "p50 ms", "p95 ms", "p99 ms", "5xx", "SSE events received", "events/mission"))
    print("status codes:", dict(codes))
    if five_xx:
        raise RuntimeError(f"{five_xx} responses were 5xx")


if __name__ == "__main__":
    main(sys.argv[1:])
