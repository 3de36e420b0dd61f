"""Container healthcheck: is *this container's* service instance alive and answering on the bus?

    python -m deploy.healthcheck renderer        # exit 0 healthy, 1 not

A service instance is healthy when its liveliness token ``ant/alive/<service>/<instance>`` is seen
through the router *and* its ``info`` queryable answers (the token alone survives a wedged
process whose zenoh threads still run). The instance is ``$ANT_INSTANCE`` when set, otherwise the
one named after this container's host name (the runner's default ``<hostname>-<pid>``). With
``--any`` any instance of the service will do (a check from outside the container).

The gateway is checked over HTTP (``GET /health`` on ``$ANT_PORT``), which is what its users need.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import sys
import urllib.request

from shared import keys
from shared.bus.config import ZenohSettings

log = logging.getLogger("healthcheck")


class Unhealthy(RuntimeError):
    """The service instance is not (yet) usable."""


def host_prefix() -> str:
    """How shared.runner names an instance without ANT_INSTANCE, minus the pid: ``<hostname>-``."""
    host = "".join(c if c.isalnum() else "-" for c in socket.gethostname())[:24].strip("-") or "host"
    return host + "-"


def pick_instance(tokens: list[str], service: str, instance: str | None, any_instance: bool) -> str:
    """The instance among alive ``tokens`` that this check is about."""
    names = [t.rsplit("/", 1)[-1] for t in tokens if t.split("/")[2:3] == [service]]
    if any_instance:
        if not names:
            raise Unhealthy(f"no {service} instance alive")
        return names[0]
    if instance:
        if instance not in names:
            raise Unhealthy(f"{service} instance {instance!r} not alive (alive: {names})")
        return instance
    mine = [n for n in names if n.startswith(host_prefix())]
    if not mine:
        raise Unhealthy(f"no {service} instance of host {socket.gethostname()!r} alive (alive: {names})")
    return mine[0]


def check_bus(service: str, settings: ZenohSettings, *, instance: str | None = None, any_instance: bool = False,
              timeout_s: float = 3.0) -> str:
    """Raise :class:`Unhealthy` unless the instance is alive and its info queryable answers; return it."""
    from shared.bus.typed import RemoteError, TypedBus
    from shared.bus.zenoh_bus import ZenohBus
    from shared.schemas import Ping, ServiceInfo

    with ZenohBus(settings) as bus:
        name = pick_instance(bus.alive(keys.ALIVE.pattern(service=service), timeout_s=timeout_s), service,
                             instance, any_instance)
        try:
            info = TypedBus(bus, "healthcheck").request(keys.INFO.format(service=service, instance=name), Ping(),
                                                        ServiceInfo, timeout_s=timeout_s)
        except RemoteError as exc:
            raise Unhealthy(f"{service}/{name} is alive but its info queryable failed: {exc}") from exc
        if info.service != service:
            raise Unhealthy(f"{service}/{name} answered as {info.service!r}")
        if not info.healthy:
            raise Unhealthy(f"{service}/{name} is alive but its state is broken: {info.problem}")
        return name


def check_http(url: str, timeout_s: float = 3.0) -> None:
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp:  # noqa: S310 - a fixed local URL
            body = json.loads(resp.read() or b"{}")
    except (OSError, ValueError) as exc:
        raise Unhealthy(f"{url}: {exc}") from exc
    if body.get("status") != "ok":
        raise Unhealthy(f"{url} answered {body}")


def client_settings() -> ZenohSettings:
    """The service's own zenoh settings (ANT_ZENOH__*, ZENOH_CONFIG), but as a client.

    Client mode: a healthcheck that runs every few seconds must not join the peer mesh (every
    peer would open a link to it) - it only asks the router.
    """
    from shared.runner import ServiceSettings

    env = ServiceSettings().zenoh
    connect = env.connect or ["tcp/127.0.0.1:7447"]
    # The service's own credentials: an authenticated router refuses an anonymous session.
    return env.model_copy(update={"mode": "client", "connect": connect})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="healthcheck of one service instance")
    ap.add_argument("service", choices=["router", "robot_io", "mapper", "reconstructor", "renderer", "planner",
                                        "gateway"])
    ap.add_argument("--instance", default=os.environ.get("ANT_INSTANCE") or None)
    ap.add_argument("--any", action="store_true", help="any instance of the service will do")
    ap.add_argument("--timeout-s", type=float, default=3.0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="healthcheck: %(message)s")
    try:
        if args.service == "gateway":
            port = int(os.environ.get("ANT_PORT", "8000"))
            check_http(f"http://127.0.0.1:{port}/health", args.timeout_s)
        elif args.service == "router":
            # the router is healthy when a client session can be opened through it
            from shared.bus.zenoh_bus import ZenohBus

            with ZenohBus(client_settings()):
                pass
        else:
            check_bus(args.service, client_settings(), instance=args.instance, any_instance=args.any,
                      timeout_s=args.timeout_s)
    except Exception as exc:  # any failure is "unhealthy": the exit code is what Docker reads
        log.warning("%s unhealthy: %s", args.service, exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
