"""Typed errors of the planner core."""

from __future__ import annotations


class PlannerError(Exception):
    """Base of every planner-core error."""


class ContextError(PlannerError, ValueError):
    """A step context is inconsistent (no candidates, duplicate indices, bad shapes)."""


class AnswerError(PlannerError, ValueError):
    """A policy's answer could not be parsed or names no valid candidate."""


class PolicyBackendError(PlannerError):
    """A policy backend failed (endpoint unreachable, timed out after retries, bad response)."""


class ReplayMissError(PolicyBackendError):
    """A read-only replay cache has no decision for this prompt."""
