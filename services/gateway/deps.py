"""FastAPI dependencies: the bus and settings live on app.state, opened once in the lifespan."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from services.gateway.settings import GatewaySettings
from shared.bus.typed import TypedBus


def get_bus(request: Request) -> TypedBus:
    return request.app.state.bus


def get_settings(request: Request) -> GatewaySettings:
    return request.app.state.settings


BusDep = Annotated[TypedBus, Depends(get_bus)]
SettingsDep = Annotated[GatewaySettings, Depends(get_settings)]
