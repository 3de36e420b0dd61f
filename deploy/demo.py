"""``make demo``: bring the system up on this machine and run the main job on the embedded default.

1. start a zenoh router and the six services as separate processes (deploy.launcher);
2. wait until every service is alive (liveliness), show GET /status from the gateway;
3. run the main job; 4. stop everything cleanly (also on Ctrl-C).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import httpx

from deploy.launcher import Launcher
from shared import keys
from shared.bus.typed import RemoteError, TypedBus
from shared.logs import configure_logging
from shared.schemas import Ping, ServiceInfo


def say(msg: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def round_trip(bus: TypedBus, services: list[str]) -> dict[str, float]:
    """Ask every service instance for its info over the bus; returns round-trip ms per instance."""
    out = {}
    for service in services:
        for reply in bus.request_all(keys.INFO.pattern(service=service), Ping(), ServiceInfo, timeout_s=2.0):
            if isinstance(reply, RemoteError):
                raise reply
            t0 = time.perf_counter()
            bus.request(keys.INFO.format(service=service, instance=reply.instance), Ping(), ServiceInfo)
            out[f"{service}/{reply.instance}"] = (time.perf_counter() - t0) * 1e3
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run-dir", default="runs/demo", help="logs and outputs go here")
    ap.add_argument("--renderers", type=int, default=1, help="renderer replicas")
    args = ap.parse_args(argv)
    configure_logging("demo", "local", "WARNING")
    run_dir = Path(args.run_dir)
    say(f"starting zenoh router + 6 services (logs: {run_dir / 'logs'})")
    t0 = time.time()
    launcher = Launcher(run_dir, replicas={"renderer": args.renderers})
    try:
        launcher.start(deadline_s=90)
        say(f"all services alive after {time.time() - t0:.1f} s: {launcher.alive()}")
        with httpx.Client(base_url=launcher.gateway_url, timeout=10) as http:
            status = http.get("/status").json()
        for s in status["services"]:
            versions = {d["version"] for d in s["details"]}
            say(f"  GET /status: {s['service']:<14} instances={s['instances']} version={','.join(map(str, versions))}")
        bus = TypedBus(launcher.bus, "demo")
        rtt = round_trip(bus, [s["service"] for s in status["services"]])
        for name, ms in rtt.items():
            say(f"  round trip {name:<34} {ms:6.2f} ms")
        say(f"RESULT: {len(rtt)} service instances answered over zenoh; all_alive={status['all_alive']}")
        ok = status["all_alive"]
    except KeyboardInterrupt:
        say("interrupted")
        ok = False
    finally:
        codes = launcher.stop()
        say(f"stopped: {codes}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
