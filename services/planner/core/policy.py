"""The policy port: ``decide(ctx) -> Decision``, backends registered by name.

    policy = POLICIES.create("heuristic", {})
    with policy:
        policy.reset("mission-1")
        decision = policy.decide(ctx)
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from shared.registry import Registry
from shared.schemas import Decision, UsageData

from .context import StepContext


class Policy(ABC):
    """A navigation policy. Implementations are registered in :data:`POLICIES`."""

    name: str = "policy"

    def __init__(self) -> None:
        self.mission_id = ""
        self.usage = UsageData()

    def reset(self, mission_id: str) -> None:
        """Start a new mission: clears per-mission state and the usage counters."""
        self.mission_id = mission_id
        self.usage = UsageData()

    @abstractmethod
    def decide(self, ctx: StepContext) -> Decision:
        """Choose one of ``ctx.candidates``; the returned ``candidate_index`` is always one of them."""

    def close(self) -> None:
        """Release resources (HTTP clients, cache files)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _decision(self, ctx: StepContext, index: int, reasoning: str = "", **kw) -> Decision:
        view = ctx.candidate(index)
        kw.setdefault("backend", self.name)
        return Decision(candidate_index=index, kind=view.kind, reasoning=reasoning, **kw)


POLICIES: Registry[Policy] = Registry[Policy]("policy")
