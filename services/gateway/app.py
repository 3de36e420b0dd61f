"""The gateway: HTTP in front of the bus. It never does navigation work itself."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware

import shared
from services.gateway.routes import health, status
from services.gateway.settings import GatewaySettings
from shared.bus.base import Bus
from shared.runner import Node, RunningService, Service


class GatewayService(Service):
    """The gateway's presence on the bus: liveliness, info and metrics like every service."""

    name = "gateway"
    Settings = GatewaySettings

    def start(self, node: Node) -> None:
        pass


def _zenoh_bus(settings: GatewaySettings) -> Bus:
    from shared.bus.zenoh_bus import ZenohBus

    return ZenohBus(settings.zenoh)


def create_app(settings: GatewaySettings | None = None,
               bus_factory: Callable[[GatewaySettings], Bus] = _zenoh_bus) -> FastAPI:
    settings = settings or GatewaySettings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        bus = bus_factory(settings)
        running = RunningService(GatewayService(settings), bus)
        app.state.settings = settings
        app.state.bus = running.node.bus
        try:
            yield
        finally:
            running.close()
            bus.close()

    app = FastAPI(title="SpatialAnt gateway", version=shared.__version__, lifespan=lifespan)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["*"],
                           allow_headers=["*"])
    app.include_router(health.router)
    app.include_router(status.router)
    return app
