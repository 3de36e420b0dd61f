"""Typed errors of the renderer core."""

from __future__ import annotations


class RendererError(Exception):
    """Base of every error raised by the renderer core."""


class EmptyCloudError(RendererError):
    """The cloud has no points, so there is nothing to render or map."""


class CloudFormatError(RendererError):
    """A cloud's arrays have the wrong shape or dtype, or a cloud file cannot be read."""


class BackendUnavailableError(RendererError):
    """A backend was asked for a device it cannot use (e.g. ``cuda`` without a GPU)."""
