"""Typed errors of the renderer service's core (the point renderer's own are in :mod:`libs.pointrender`)."""

from __future__ import annotations

from libs.pointrender.errors import BackendUnavailableError, RendererError

__all__ = ["BackendUnavailableError", "MapMismatchError", "RendererError"]


class MapMismatchError(RendererError, LookupError):
    """A map renderer bound to one map was asked for another."""
