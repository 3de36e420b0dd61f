from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel

import shared

router = APIRouter(tags=["health"])


class Health(BaseModel):
    status: str
    version: str


@router.get("/health", response_model=Health)
def health() -> Health:
    """The gateway process is up (it says nothing of the other services: see /status)."""
    return Health(status="ok", version=shared.__version__)
