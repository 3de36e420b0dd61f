"""``make up``: the whole system, locally, until Ctrl-C - submit missions over HTTP as you would in production.

Starts a zenoh router and every service as its own process (the same :class:`deploy.launcher.Launcher`
as ``make demo``, with crash restarts), on a fixed gateway port, prints the dashboard URL and the API
token, and stays up until Ctrl-C or SIGTERM, then stops every process. Maps, the gateway database and
the logs persist in ``--run-dir``, so a second ``make up`` finds the missions and maps of the first.

The API token is generated at the first start and kept in ``<run-dir>/api_token`` (mode 0600), so it
never needs to be committed or typed twice; ``ANT_API_TOKEN`` overrides it, ``--no-token`` leaves the
API open (loopback only by default, so nothing outside this machine can reach it).
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import sys
import threading
from pathlib import Path

from deploy.launcher import Launcher, Stopped
from shared.logs import configure_logging

DEFAULT_PORT = 8080


def api_token(run_dir: Path) -> str:
    """The token of this run directory: ``ANT_API_TOKEN``, else the stored one, else a new one."""
    if os.environ.get("ANT_API_TOKEN"):
        return os.environ["ANT_API_TOKEN"]
    path = run_dir / "api_token"
    if path.is_file():
        token = path.read_text().strip()
        if token:
            return token
    run_dir.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(24)
    # Created with 0600 from the start: the token is never readable by other users, not even briefly.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(token + "\n")
    return token


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run-dir", default="runs/up", help="maps, the gateway database, logs and the token")
    ap.add_argument("--port", type=int, default=int(os.environ.get("ANT_UP_PORT", DEFAULT_PORT)),
                    help=f"the gateway's HTTP port (default {DEFAULT_PORT}, or ANT_UP_PORT)")
    ap.add_argument("--host", default="127.0.0.1", help="the gateway's listen address (0.0.0.0: other hosts)")
    ap.add_argument("--scene", default="generated:0", help="robot-io's scene: generated:<seed>[:floors=2] or a mesh")
    ap.add_argument("--renderers", type=int, default=1, help="renderer replicas")
    ap.add_argument("--no-token", action="store_true", help="leave the HTTP API open (no bearer token)")
    ap.add_argument("--deadline-s", type=float, default=180.0, help="how long the services may take to start")
    return ap


def main(argv: list[str] | None = None, stop: threading.Event | None = None) -> int:
    """Run until ``stop`` is set or a stop signal comes (SIGINT, SIGTERM, SIGHUP); returns 0 on a clean stop."""
    args = build_parser().parse_args(argv)
    configure_logging("up", "local", "WARNING")
    if not 0 < args.port < 65536:
        print(f"up: --port must be 1-65535, got {args.port}", file=sys.stderr)
        return 2
    run_dir = Path(args.run_dir).resolve()
    token = None if args.no_token else api_token(run_dir)
    env = {
        "ANT_ROBOT_CONFIG": json.dumps({"scene": args.scene}),
        "ANT_STORE_DIR": str(run_dir / "maps"),
        "ANT_DB_PATH": str(run_dir / "gateway.sqlite3"),
        "ANT_HOST": args.host,
    }
    if token:
        env["ANT_API_TOKEN"] = token
    stop = stop or threading.Event()
    launcher = Launcher(run_dir, replicas={"renderer": args.renderers}, gateway_port=args.port, extra_env=env)
    print(f"up: starting a zenoh router and {len(launcher.services)} services (logs: {run_dir / 'logs'})", flush=True)
    # SIGINT, SIGTERM and SIGHUP raise Stopped while the launcher is started (deploy.launcher's one
    # lifecycle); the finally below stops every process, whether the signal came while starting or serving.
    try:
        try:
            launcher.start(deadline_s=args.deadline_s)
        except Exception as exc:
            print(f"up: FAILED to start: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
            return 1
        _serve(args, run_dir, token, stop)
    except Stopped as sig:
        print(f"up: {sig}: stopping", flush=True)
    finally:
        codes = launcher.stop()
        print(f"up: stopped every process: {codes}", flush=True)
    return 0


def _serve(args: argparse.Namespace, run_dir: Path, token: str | None, stop: threading.Event) -> None:
    host = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
    url = f"http://{host}:{args.port}"
    print(f"up: dashboard  {url}/dashboard", flush=True)
    print(f"up: API docs   {url}/docs", flush=True)
    if token:
        print(f"up: API token  {token}   (kept in {run_dir / 'api_token'}; send 'Authorization: Bearer <token>')",
              flush=True)
    else:
        print("up: API token  none (--no-token: the API is open)", flush=True)
    print(f"up: try        curl -s -X POST {url}/explorations -H 'Authorization: Bearer {token or ''}' "
          "-H 'Content-Type: application/json' -d '{\"map_id\": \"house\"}'", flush=True)
    print("up: running; Ctrl-C (or SIGTERM, SIGHUP) stops every process", flush=True)
    stop.wait()


if __name__ == "__main__":
    sys.exit(main())
