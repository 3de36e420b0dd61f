"""The gateway: HTTP in front of the bus. It never does navigation work itself.

It opens the bus (zenoh, or a fake one in tests), the SQLite store and the event ingest in its
lifespan; routers per resource (missions, explorations, maps, status, health, dashboard) only call
them through the dependencies of :mod:`services.gateway.deps`.
"""

from __future__ import annotations

import asyncio
import logging
import re
import threading
from collections.abc import Callable
from contextlib import asynccontextmanager

import anyio.to_thread
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

import shared
from services.gateway import deps, errors
from services.gateway.cache import RecordCache
from services.gateway.events import EventHub, EventIngest
from services.gateway.limits import BodyLimit
from services.gateway.reaper import JobReaper
from services.gateway.routes import dashboard, downloads, explorations, health, maps, metrics, missions, robot, status
from services.gateway.settings import GatewaySettings
from services.gateway.store import GatewayStore
from shared.bus.base import Bus
from shared.runner import Node, RunningService, Service

log = logging.getLogger(__name__)


class GatewayService(Service):
    """The gateway's presence on the bus: liveliness, info and metrics like every service."""

    name = "gateway"
    Settings = GatewaySettings

    def backends(self) -> dict[str, str]:
        return {"store": "sqlite-wal", "auth": "bearer" if self.settings.api_token else "open"}

    def start(self, node: Node) -> None:
        pass


def _zenoh_bus(settings: GatewaySettings) -> Bus:
    from shared.bus.zenoh_bus import ZenohBus

    return ZenohBus(settings.zenoh)


_TOKEN_IN_URL = re.compile(r"(access_token=)[^&\s\"]*")


class RedactTokens(logging.Filter):
    """Keep ``?access_token=`` values (how an EventSource or <img> of the dashboard sends its read
    token) out of the logs: uvicorn's access log writes every request's full path."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(_TOKEN_IN_URL.sub(r"\1***", a) if isinstance(a, str) else a for a in record.args)
        if isinstance(record.msg, str):
            record.msg = _TOKEN_IN_URL.sub(r"\1***", record.msg)
        return True


def _redact_access_log() -> None:
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactTokens) for f in access.filters):
        access.addFilter(RedactTokens())


def create_app(settings: GatewaySettings | None = None,
               bus_factory: Callable[[GatewaySettings], Bus] = _zenoh_bus) -> FastAPI:
    settings = settings or GatewaySettings()
    _redact_access_log()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # Sync routes wait on the bus in threads (up to request_timeout_s each): anyio's default of
        # 40 threads lets a burst of slow bus calls queue every other sync route behind them.
        anyio.to_thread.current_default_thread_limiter().total_tokens = settings.threadpool_workers
        store = GatewayStore(settings.db_path)
        hub = EventHub(asyncio.get_running_loop())
        bus = bus_factory(settings)
        running = RunningService(GatewayService(settings), bus)
        app.state.settings = settings
        app.state.bus = running.node.bus
        app.state.store = store
        app.state.hub = hub
        app.state.records = RecordCache(store, settings.record_cache_jobs)
        # Held while the robot switches scenes: no mission or exploration may start meanwhile.
        app.state.scene_lock = threading.Lock()
        # Subscribed before the first request: every event published from now on is stored.
        app.state.ingest = EventIngest(running.node.bus, store, hub, settings.robot)
        # Jobs whose worker is gone (died, or restarted and forgot them) end as failed, with the reason:
        # checked at start, periodically and whenever a worker's token drops.
        app.state.reaper = JobReaper(running.node.bus, store, hub, interval_s=settings.reconcile_interval_s)
        app.state.recordings = downloads.RecordingWriter(running.node.bus, store, settings)
        log.info("gateway on %s:%d, database %s", settings.host, settings.port, settings.db_path)
        try:
            yield
        finally:
            app.state.recordings.close()
            app.state.reaper.close()
            app.state.ingest.close()
            hub.close()
            running.close()
            bus.close()
            store.close()

    app = FastAPI(title="SpatialAnt gateway", version=shared.__version__, lifespan=lifespan,
                  description="Missions, explorations and maps of the SpatialAnt robot; live events over SSE.")
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes, upload_max_bytes=settings.max_upload_bytes,
                       upload_paths=("/maps",))
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["*"],
                           allow_headers=["*"], expose_headers=["Location"])
    errors.install(app)
    for module in (health, dashboard):  # liveness probes and the page itself stay open
        app.include_router(module.router)
    for module in (status, metrics, missions, explorations, maps, robot, downloads):
        app.include_router(module.router, dependencies=[deps.ReadAuthorized])
    app.mount("/static", StaticFiles(directory=dashboard.STATIC_DIR), name="static")
    return app
