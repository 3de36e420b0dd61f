"""The policy port: ``decide(ctx) -> Decision``, backends registered by name.

    policy = POLICIES.create("heuristic", {})
    with policy:
        policy.reset("mission-1")
        decision = policy.decide(ctx)
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

from shared.registry import Registry
from shared.schemas import Decision

from .context import StepContext


@dataclass
class Usage:
    """LLM usage accumulated over one mission."""

    calls: int = 0
    prompt_tokens: int = 0
    completion_tokens: int = 0
    cost_usd: float = 0.0
    reasks: int = 0
    fallbacks: int = 0
    cache_hits: int = 0

    def add(self, other: Usage) -> None:
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def to_dict(self) -> dict:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


class Policy(ABC):
    """A navigation policy. Implementations are registered in :data:`POLICIES`."""

    name: str = "policy"

    def __init__(self) -> None:
        self.mission_id = ""
        self.usage = Usage()

    def reset(self, mission_id: str) -> None:
        """Start a new mission: clears per-mission state and the usage counters."""
        self.mission_id = mission_id
        self.usage = Usage()

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
