"""FastAPI dependencies: the bus, store, hub and settings live on app.state, opened once in the lifespan."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from services.gateway.cache import RecordCache
from services.gateway.events import EventHub
from services.gateway.settings import GatewaySettings
from services.gateway.store import GatewayStore
from shared.bus.typed import TypedBus

_bearer = HTTPBearer(auto_error=False, description="the gateway's API token (ANT_API_TOKEN), when one is set")


def get_bus(request: Request) -> TypedBus:
    return request.app.state.bus


def get_settings(request: Request) -> GatewaySettings:
    return request.app.state.settings


def get_store(request: Request) -> GatewayStore:
    return request.app.state.store


def get_hub(request: Request) -> EventHub:
    return request.app.state.hub


def get_cache(request: Request) -> RecordCache:
    return request.app.state.records


def require_token(request: Request,
                  credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Routes that change something need ``Authorization: Bearer <token>`` when a token is configured."""
    expected = request.app.state.settings.api_token
    if not expected:
        return
    given = credentials.credentials if credentials else ""
    # compare_digest: the time taken must not tell how much of a guess was right.
    if not secrets.compare_digest(given.encode(), expected.encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED,
                            "missing or wrong bearer token" if given else "this route needs a bearer token",
                            headers={"WWW-Authenticate": "Bearer"})


def require_read(request: Request,
                 credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """With ``ANT_READ_TOKEN`` set, reading (missions, images, maps, status) needs that token or the API
    token, as ``Authorization: Bearer`` or ``?access_token=`` (an EventSource or an <img> cannot send
    headers). Without it, reads stay open."""
    settings = request.app.state.settings
    if not settings.read_token:
        return
    given = credentials.credentials if credentials else request.query_params.get("access_token", "")
    ok = any(t and secrets.compare_digest(given.encode(), t.encode()) for t in (settings.read_token, settings.api_token))
    if not ok:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED,
                            "missing or wrong read token" if given else "reading needs a bearer token",
                            headers={"WWW-Authenticate": "Bearer"})


BusDep = Annotated[TypedBus, Depends(get_bus)]
SettingsDep = Annotated[GatewaySettings, Depends(get_settings)]
StoreDep = Annotated[GatewayStore, Depends(get_store)]
HubDep = Annotated[EventHub, Depends(get_hub)]
CacheDep = Annotated[RecordCache, Depends(get_cache)]
Authorized = Depends(require_token)
ReadAuthorized = Depends(require_read)
