"""The one way every service process runs (``python -m services.<name>``).

A service is a class with a ``name``, a settings class and a ``start(node)`` that declares its
queryables and subscriptions through the :class:`Node`. The runner gives it:

* typed settings from the environment (``ANT_...``, nested with ``__``) and the command line;
* a bus: zenoh built from the settings (or a fake one in unit tests);
* a liveliness token ``ant/alive/{service}/{instance}``, an ``info`` and a ``metrics`` queryable;
* structured logging; a graceful stop on SIGTERM/SIGINT (every entity undeclared, the session closed).

Handlers registered through ``node.serve`` turn any exception into a typed error reply and keep serving.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import socket
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import ClassVar, Generic, TypeVar

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

import shared
from shared import keys
from shared.bus.base import Bus, Closeable
from shared.bus.config import ZenohSettings
from shared.bus.typed import TypedBus
from shared.logs import configure_logging
from shared.schemas import Message, Ping, ServiceInfo
from shared.telemetry import Telemetry

log = logging.getLogger(__name__)

Req = TypeVar("Req", bound=Message)


def _default_instance() -> str:
    host = "".join(c if c.isalnum() else "-" for c in socket.gethostname())[:24].strip("-") or "host"
    return f"{host}-{os.getpid()}"


class ServiceSettings(BaseSettings):
    """Settings every service shares; services subclass it to add their own."""

    model_config = SettingsConfigDict(env_prefix="ANT_", env_nested_delimiter="__", extra="ignore")

    robot: str = Field("robot0", description="robot id used in key expressions")
    instance: str = Field(default_factory=_default_instance, description="unique per process")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    log_level: str = "INFO"
    log_json: bool = False
    workers: int = Field(2, ge=1, le=64, description="threads serving each queryable")
    max_queue: int = Field(64, ge=1, le=10_000, description="queries waiting before 'overloaded'")

    @field_validator("robot", "instance")
    @classmethod
    def _segment(cls, v: str) -> str:
        return keys.validate_segment(v)


class FleetServiceSettings(ServiceSettings):
    """Settings of a service that serves many robots at once (the planner, the mapper): it answers on a
    wildcard in the robot segment and keeps one job queue per robot."""

    serve_robots: list[str] = Field(default_factory=list, description=(
        "robot ids this instance serves; empty: every robot (a wildcard). Replicas given disjoint lists "
        "split the robots between them"))
    max_robots: int = Field(64, ge=1, le=1024, description="robots with a job queue at once (each one a thread)")

    @field_validator("serve_robots")
    @classmethod
    def _robot_ids(cls, v: list[str]) -> list[str]:
        return [keys.validate_segment(r, "robot id") for r in v]


S = TypeVar("S", bound=ServiceSettings)


class Node:
    """What a service sees of the runtime: its identity, the typed bus, telemetry."""

    def __init__(self, service: str, settings: ServiceSettings, bus: Bus):
        self.service = service
        self.settings = settings
        self.instance = settings.instance
        self.robot = settings.robot
        self.telemetry = Telemetry(service, settings.instance)
        self.bus = TypedBus(bus, service, self.telemetry)
        self._entities: list[Closeable] = []

    def own(self, entity: Closeable) -> Closeable:
        self._entities.append(entity)
        return entity

    def serve(self, key: str, model: type[Req], handler: Callable[..., Message], *,
              workers: int | None = None, name: str | None = None, replicated: bool = False,
              keyed: bool = False) -> Closeable:
        """Serve a queryable; ``replicated`` also serves this instance's own route so that clients
        can share load across replicas (``TypedBus.request(..., balance=service)``); ``keyed`` calls
        ``handler(key, request)`` with the concrete key asked."""
        return self.own(self.bus.serve(
            key, model, handler, workers=workers or self.settings.workers,
            max_queue=self.settings.max_queue, name=name or key.rsplit("/", 1)[-1],
            instance=self.instance if replicated else None, keyed=keyed,
        ))

    def close(self) -> None:
        for e in reversed(self._entities):
            e.close()
        self._entities.clear()
        self.bus.close()


class Service(ABC, Generic[S]):
    """Base of every service; ``Service[MySettings]`` types ``self.settings`` as ``MySettings``."""

    name: ClassVar[str]
    Settings: ClassVar[type[ServiceSettings]] = ServiceSettings

    def __init__(self, settings: S):
        self.settings: S = settings

    def backends(self) -> dict[str, str]:
        """Names of the backends this instance runs (shown in ``info`` and ``GET /status``)."""
        return {}

    def health(self) -> str | None:
        """None while this instance's state is usable, else what is wrong (``info`` then says
        ``healthy: false``; ``GET /status`` and the container healthcheck report it)."""
        return None

    @abstractmethod
    def start(self, node: Node) -> None:
        """Declare queryables/subscriptions. Must return promptly; long work goes to threads."""

    def stop(self) -> None:
        """Release what ``start`` acquired beyond the node's entities."""


class RunningService:
    """A started service on a bus: ``with RunningService(svc, bus): ...``; tests use it directly."""

    def __init__(self, service: Service, bus: Bus):
        self.service = service
        self.node = Node(service.name, service.settings, bus)
        started = time.time()
        info = ServiceInfo(service=service.name, version=shared.__version__, instance=self.node.instance,
                           backends=service.backends(), started_s=started)

        def current_info(_: Ping) -> ServiceInfo:
            try:
                problem = service.health()
            except Exception as exc:  # a health check that fails is itself a problem to report
                problem = f"health check failed: {type(exc).__name__}: {exc}"
            return info if problem is None else info.model_copy(update={"healthy": False, "problem": problem})

        parts = {"service": service.name, "instance": self.node.instance}
        self.node.serve(keys.INFO.format(**parts), Ping, current_info, workers=1, name="info")
        self.node.serve(keys.METRICS.format(**parts), Ping, lambda _: self.node.telemetry.snapshot(),
                        workers=1, name="metrics")
        service.start(self.node)
        # The token goes last: whoever sees it alive can use every queryable at once.
        self.node.own(bus.liveliness_token(keys.ALIVE.format(**parts)))
        log.info("%s %s started (backends: %s)", service.name, self.node.instance, service.backends())

    def close(self) -> None:
        self.node.close()
        self.service.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def freeze_started_heap() -> None:
    """Called by a long-running process (a service, the gateway, the ROS 2 stand-in) once it has started:
    everything it holds by then (imported modules, loaded kernels, its scene) moves out of the cyclic
    garbage collector's reach (``gc.freeze``), where it stays until the process ends.

    Why: the interpreter's shutdown walks every tracked object in its collections, and a service's
    ~70-180 thousand (numpy, scipy, numba, pydantic, the product) made its exit after a SIGTERM cost 0.2-0.5 s
    of CPU (robot-io 0.45, mapper, renderer and reconstructor 0.36-0.39, planner 0.20), ~0.03-0.05 s
    frozen: a launched system of 8 services stopped in 2.6 s of wall time instead of 0.25 s (2 cores,
    load average 12). The full collections while it runs skip them too. Frozen objects are still freed by
    reference counting; only garbage cycles among them would stay, and a full collection at that point
    found 0-240 unreachable objects in the services.
    """
    gc.freeze()


def run(service_cls: type[Service], argv: list[str] | None = None) -> int:
    """Entry point of ``python -m services.<name>``: settings, zenoh, serve until a signal."""
    from shared.bus.zenoh_bus import ZenohBus  # entry points alone import zenoh

    settings = service_cls.Settings(_cli_parse_args=argv if argv is not None else True)
    configure_logging(service_cls.name, settings.instance, settings.log_level, settings.log_json)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        with ZenohBus(settings.zenoh) as bus, RunningService(service_cls(settings), bus):
            freeze_started_heap()
            stop.wait()
            log.info("stopping")
        log.info("stopped")
    except Exception:
        log.exception("%s failed", service_cls.name)
        return 1
    return 0
