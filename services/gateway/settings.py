"""Gateway settings from the environment (``ANT_...``) and command line."""

from __future__ import annotations

from pydantic import Field

from shared.runner import ServiceSettings


class GatewaySettings(ServiceSettings):
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    api_token: str | None = Field(None, description="bearer token required by mutating routes")
    cors_origins: list[str] = Field(default_factory=list)
    status_timeout_s: float = Field(1.0, gt=0, le=30)
