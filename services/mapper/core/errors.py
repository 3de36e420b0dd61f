"""Typed errors of the mapper core."""

from __future__ import annotations


class MapperError(Exception):
    """Base of every error raised by the mapper core."""


class PredictorError(MapperError):
    """The waypoint predictor cannot work on its input (bad panorama, bad config)."""


class ExplorationError(MapperError):
    """Exploration could not start or continue (no observation, robot refused to move...)."""


class PlanningError(MapperError):
    """Tour planning failed for a region (no reachable cell, no hub candidate...)."""


class TourExecutionError(MapperError):
    """A planned tour could not be driven (the robot never reached its start, ...)."""
