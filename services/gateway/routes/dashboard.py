"""The dashboard: plain HTML/JS/CSS served by the gateway (no build step)."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, RedirectResponse

STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
router = APIRouter(tags=["dashboard"], include_in_schema=False)


@router.get("/", response_class=RedirectResponse)
def root() -> RedirectResponse:
    return RedirectResponse("/dashboard")


@router.get("/dashboard", response_class=FileResponse)
def dashboard() -> FileResponse:
    """Submit missions, watch them live, browse maps and missions."""
    return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})
