"""Gateway under load: 200 concurrent clients poll ``GET /missions/{id}`` and hold an SSE stream each.

The gateway runs as its own process (``python -m services.gateway``) on 127.0.0.1 over a real zenoh
bus; a scripted planner and reconstructor in this process publish live mission events (with JPEGs)
while the clients hammer it for ``--duration-s`` seconds (30 by default). Loopback only, bounded in
clients (at most 2000) and time.

The clients run in a process of their own on a minimal HTTP/1.1 keep-alive client (one connection
for polls and one for the stream per client): a general-purpose client (httpx) with 400 pooled
connections spent more CPU per request than the gateway did, and sharing a GIL with the scripted
planner put that planner's work into the measured latencies. ``--conditional`` makes the polls send
the ETag they last got in ``If-None-Match``, as a browser revalidating a ``no-cache`` record does.
Prints zero-5xx check, request counts, 304 share and p50/p99 latency.

    python -m bench.gateway [--clients 200] [--duration-s 30] [--conditional]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import random
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import httpx

from bench.common import percentiles_ms, table, wait_gateway
from deploy.launcher import free_port
from tests.doubles.scripted_services import ScriptedPlanner, ScriptedReconstructor
from shared.bus.config import ZenohSettings
from shared.bus.typed import TypedBus

REPO = Path(__file__).resolve().parents[1]
HOST = "127.0.0.1"  # loopback only, whatever the arguments
MAX_CLIENTS = 2000


class _Http:
    """One HTTP/1.1 keep-alive connection: just enough protocol for GETs of JSON and an SSE stream."""

    def __init__(self, port: int):
        self.port = port
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def _send(self, path: str, headers: dict[str, str]) -> tuple[int, dict[bytes, bytes]]:
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(HOST, self.port)
        extra = "".join(f"{k}: {v}\r\n" for k, v in headers.items())
        self.writer.write(f"GET {path} HTTP/1.1\r\nHost: {HOST}:{self.port}\r\n{extra}\r\n".encode())
        head = await self.reader.readuntil(b"\r\n\r\n")
        lines = head.split(b"\r\n")
        status = int(lines[0].split(b" ", 2)[1])
        hdrs = {}
        for line in lines[1:]:
            if b":" in line:
                k, v = line.split(b":", 1)
                hdrs[k.strip().lower()] = v.strip()
        return status, hdrs

    async def get(self, path: str, headers: dict[str, str]) -> tuple[int, dict[bytes, bytes], bytes]:
        try:
            status, hdrs = await self._send(path, headers)
            if status in (204, 304) or status < 200:
                body = b""
            elif b"content-length" in hdrs:
                body = await self.reader.readexactly(int(hdrs[b"content-length"]))
            else:
                raise ValueError(f"unframed response {status} {hdrs}")
            if hdrs.get(b"connection", b"").lower() == b"close":
                self.close()
            return status, hdrs, body
        except BaseException:
            self.close()
            raise

    async def stream_ids(self, path: str, until: float, sse: Counter) -> int:
        status, _ = await self._send(path, {"Accept": "text/event-stream"})
        while time.monotonic() < until:
            try:
                line = await asyncio.wait_for(self.reader.readline(), max(0.01, until - time.monotonic()))
            except TimeoutError:
                break
            if not line:
                break
            if line.startswith(b"id: "):
                sse["events"] += 1
        return status

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


async def _client(port: int, mission_ids: list[str], until: float, conditional: bool, lat: list[float],
                  codes: Counter, sse: Counter, rng: random.Random) -> None:
    mid = rng.choice(mission_ids)
    poll, stream_conn = _Http(port), _Http(port)

    async def hold_stream():
        try:
            codes[f"sse {await stream_conn.stream_ids(f'/missions/{mid}/events', until, sse)}"] += 1
        except (OSError, asyncio.IncompleteReadError, ValueError) as exc:
            codes[f"sse error {type(exc).__name__}"] += 1
        finally:
            stream_conn.close()

    stream = asyncio.create_task(hold_stream())
    etags: dict[str, str] = {}
    while time.monotonic() < until:
        target = rng.choice(mission_ids)
        headers = {"If-None-Match": etags[target]} if conditional and target in etags else {}
        t0 = time.perf_counter()
        try:
            code, hdrs, _ = await poll.get(f"/missions/{target}", headers)
            lat.append(time.perf_counter() - t0)
            codes[code] += 1
            if b"etag" in hdrs:
                etags[target] = hdrs[b"etag"].decode()
        except (OSError, asyncio.IncompleteReadError, ValueError) as exc:
            codes[f"error {type(exc).__name__}"] += 1
        await asyncio.sleep(rng.uniform(0.05, 0.25))  # a polling UI, not a tight loop
    poll.close()
    await asyncio.gather(stream, return_exceptions=True)


async def _load(port: int, mission_ids: list[str], clients: int, duration_s: float, conditional: bool):
    lat: list[float] = []
    codes: Counter = Counter()
    sse: Counter = Counter()
    until = time.monotonic() + duration_s
    rngs = [random.Random(i) for i in range(clients)]
    await asyncio.gather(*(_client(port, mission_ids, until, conditional, lat, codes, sse, r) for r in rngs))
    return lat, codes, sse


def _load_process(port: int, mission_ids: list[str], clients: int, duration_s: float, conditional: bool,
                  out: mp.Queue) -> None:
    try:
        import uvloop

        run = uvloop.run
    except ImportError:
        run = asyncio.run
    t0 = time.perf_counter()
    lat, codes, sse = run(_load(port, mission_ids, clients, duration_s, conditional))
    out.put((lat, dict(codes), dict(sse), time.perf_counter() - t0))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--duration-s", type=float, default=float(os.environ.get("ANT_BENCH_GATEWAY_S", 30)))
    ap.add_argument("--missions", type=int, default=8)
    ap.add_argument("--conditional", action="store_true", help="polls send If-None-Match (304 when unchanged)")
    args = ap.parse_args(argv if argv is not None else [])
    if not 1 <= args.clients <= MAX_CLIENTS or not 0 < args.duration_s <= 600:
        ap.error(f"--clients must be 1..{MAX_CLIENTS} and --duration-s 0..600")
    from shared.bus.zenoh_bus import ZenohBus

    zport, hport = free_port(), free_port()
    url = f"http://127.0.0.1:{hport}"
    with tempfile.TemporaryDirectory() as tmp, ZenohBus(ZenohSettings(listen=[f"tcp/127.0.0.1:{zport}"])) as bus:
        typed = TypedBus(bus, "bench")
        recon = ScriptedReconstructor(typed)
        recon.add_random("bench-house", 10_000)
        # Missions that outlive the run, one step a second with ~10 JPEGs: a realistic event rate.
        steps = int(args.duration_s) + 20
        planner = ScriptedPlanner(typed, steps=steps, step_interval_s=1.0, candidates=4, image_px=128,
                                  image_variants=16)
        env = dict(os.environ, ANT_PORT=str(hport), ANT_HOST="127.0.0.1", ANT_INSTANCE="gateway-bench",
                   ANT_ZENOH__MODE="peer", ANT_ZENOH__CONNECT=f'["tcp/127.0.0.1:{zport}"]',
                   ANT_ZENOH__MULTICAST_SCOUTING="false", ANT_DB_PATH=str(Path(tmp) / "gw.sqlite3"),
                   ANT_LOG_LEVEL="WARNING", PYTHONPATH=str(REPO))
        log = open(Path(tmp) / "gateway.log", "wb")
        proc = subprocess.Popen([sys.executable, "-m", "services.gateway"], env=env, cwd=REPO, stdout=log,
                                stderr=subprocess.STDOUT)
        try:
            if not wait_gateway(url, 60.0, alive=lambda: proc.poll() is None, interval_s=0.1):
                raise RuntimeError("the gateway did not come up: " + (Path(tmp) / "gateway.log").read_text()[-2000:])
            ids = []
            for i in range(args.missions):
                r = httpx.post(f"{url}/missions", json={"instruction": f"bench mission {i}", "map_id": "bench-house",
                                                        "options": {"max_steps": 500}}, timeout=10)
                r.raise_for_status()
                ids.append(r.json()["id"])
            ctx = mp.get_context("spawn")
            results = ctx.Queue()
            loader = ctx.Process(target=_load_process, args=(hport, ids, args.clients, args.duration_s,
                                                             args.conditional, results), daemon=True)
            loader.start()
            try:
                lat, codes, sse, wall = results.get(timeout=args.duration_s + 120)
            finally:
                loader.join(10)
                if loader.is_alive():
                    loader.kill()
                    loader.join()
            codes = Counter(codes)
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
    table(f"gateway: {args.clients} clients polling GET /missions/{{id}}"
          f"{' (If-None-Match)' if args.conditional else ''} + 1 SSE stream each, "
          f"{args.duration_s:.0f} s, {args.missions} live missions",
          [(len(lat), len(lat) / wall, codes.get(304, 0) / max(1, len(lat)), p["p50"], p["p95"], p["p99"], five_xx,
            sse.get("events", 0), stored)],
          ("GET requests", "req/s", "304 share", "p50 ms", "p95 ms", "p99 ms", "5xx", "SSE events received",
           "events/mission"))
    print("status codes:", dict(codes))
    if five_xx:
        raise RuntimeError(f"{five_xx} responses were 5xx")


if __name__ == "__main__":
    main(sys.argv[1:])
