"""Service plumbing: ping, info, metrics and error replies."""

from __future__ import annotations

from enum import StrEnum

from pydantic import Field

from .base import Message


# --- service plumbing ------------------------------------------------------------------------------


class Ping(Message):
    pass


class ServiceInfo(Message):
    service: str
    version: str
    instance: str
    backends: dict[str, str] = Field(default_factory=dict)
    started_s: float = 0.0
    healthy: bool = True  # False: alive, but its state is broken (``problem`` says how)
    problem: str = ""


class EndpointStats(Message):
    requests: int = 0
    errors: int = 0
    latency_p50_ms: float = 0.0
    latency_p99_ms: float = 0.0
    queue_depth: int = 0


class ServiceMetrics(Message):
    service: str
    instance: str
    uptime_s: float
    endpoints: dict[str, EndpointStats] = Field(default_factory=dict)


class ErrorCode(StrEnum):
    BAD_REQUEST = "bad_request"  # undecodable, wrong schema, invalid fields
    NOT_FOUND = "not_found"
    UNAVAILABLE = "unavailable"
    INTERNAL = "internal"
    TIMEOUT = "timeout"
    BUDGET_EXCEEDED = "budget_exceeded"  # a well-formed request over a per-request budget


class ErrorReply(Message):
    """What a queryable answers instead of its result when something went wrong."""

    code: ErrorCode
    message: str
    service: str = ""

