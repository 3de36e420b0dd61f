"""Typed errors of the renderer core."""

from __future__ import annotations


class RendererError(Exception):
    """Base of every error raised by the renderer core."""


class EmptyCloudError(RendererError, ValueError):
    """The cloud has no points, so there is nothing to render or map.

    Also a ``ValueError``: a map with no points is bad input, so the bus answers ``bad_request``
    (naming the map) rather than ``internal``."""


class CloudFormatError(RendererError):
    """A cloud's arrays have the wrong shape or dtype, or a cloud file cannot be read."""


class BackendUnavailableError(RendererError):
    """A backend was asked for a device it cannot use (e.g. ``cuda`` without a GPU)."""


class MapMismatchError(RendererError, LookupError):
    """A map renderer bound to one map was asked for another."""
