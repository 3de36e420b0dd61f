"""Typed errors of the point renderer (a cloud's own errors live with it, in :mod:`shared.cloud`)."""

from __future__ import annotations


class RendererError(Exception):
    """Base of every error raised by the point renderer and the renderer service's core."""


class BackendUnavailableError(RendererError):
    """A backend was asked for a device it cannot use (e.g. ``cuda`` without a GPU)."""
