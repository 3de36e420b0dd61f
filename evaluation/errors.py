"""Typed errors of the evaluation tools (the runner, presets and the episode-set generator)."""

from __future__ import annotations


class EvaluationError(Exception):
    """Base of every error raised by :mod:`evaluation` (except :class:`shared.vln_metrics.MetricsError`)."""


class ConfigError(EvaluationError, ValueError):
    """An invalid run, preset or generator configuration."""


class GatewayError(EvaluationError):
    """The gateway answered with an error status (``status`` is the HTTP code, 0 when unreachable)."""

    def __init__(self, message: str, status: int = 0):
        super().__init__(message)
        self.status = status


class MissionTimeout(EvaluationError, TimeoutError):
    """A mission or exploration did not end within its deadline."""


class SceneSwitchError(EvaluationError):
    """The robot could not be switched to an episode's scene."""


class MapUnavailable(EvaluationError):
    """No map could be obtained for a scene (exploration failed, upload refused, ...)."""


class ExplorationStopped(EvaluationError):
    """The run stopped (its budget was reached) while a robot explored a scene to build its map: the
    exploration was cancelled through its gateway, and the scene's episodes were not started."""

    def __init__(self, scene_id: str, exploration_id: str, state: str, stage: str | None, why: str):
        where = f" while {stage}" if stage else ""
        super().__init__(f"the exploration {exploration_id} building the map of {scene_id} was {state}{where} "
                         f"({why})")
        self.scene_id, self.exploration_id, self.state = scene_id, exploration_id, state
        self.stage, self.why = stage, why


class ResultsFormatError(EvaluationError):
    """A results file that cannot be read (not the runner's JSON lines)."""
