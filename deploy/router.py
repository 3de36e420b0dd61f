"""A zenoh router process (zenoh itself in router mode; no home-made broker).

    python -m deploy.router --listen tcp/127.0.0.1:7447

In production, use the official ``eclipse/zenoh`` router image with ``deploy/zenoh/router.json5``;
this entry point is what the local launcher and the tests use when no zenohd binary is installed.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from shared.bus.config import ZenohSettings, zenoh_config
from shared.logs import configure_logging

log = logging.getLogger("router")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--listen", action="append", default=[], help="endpoint, repeatable")
    ap.add_argument("--config", default=None, help="zenoh JSON5 config file")
    args = ap.parse_args(argv)
    configure_logging("router", "zenoh")
    import zenoh

    settings = ZenohSettings(mode="router", listen=args.listen or ["tcp/127.0.0.1:7447"],
                             config_file=args.config)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with zenoh.open(zenoh_config(settings)) as session:
        log.info("zenoh router %s listening on %s", session.zid(), settings.listen)
        stop.wait()
    log.info("router stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
