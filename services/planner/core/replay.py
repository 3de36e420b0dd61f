"""The replay policy: a decision cache keyed by the prompt's content hash, wrapping any backend.

Re-running an evaluation hits the cache and costs no API calls; the decisions are exactly those recorded.
The cache is a JSON-lines file (append-only, human-readable, safe to interrupt: a torn last line is
ignored on load).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

from pydantic import Field

from shared.registry import BackendConfig
from shared.schemas import Decision

from .context import StepContext
from .errors import ReplayMissError
from .policy import POLICIES, Policy
from .prompt import PromptBuilder, PromptConfig
from .providers import profile

# The inner backend's settings that change the prompt's images (see openai_policy.OpenAIConfig).
_LAYOUT_KEYS = ("layout", "max_images_per_prompt", "max_image_px", "profile", "profile_overrides")

log = logging.getLogger(__name__)


class ReplayConfig(BackendConfig):
    """``inner`` is the backend to call on a cache miss (``mode='read_write'``)."""

    path: str = "replay_cache.jsonl"
    inner: str = "heuristic"
    inner_config: dict[str, Any] = Field(default_factory=dict)
    mode: Literal["read_write", "read_only"] = "read_write"
    namespace: str = ""  # e.g. the model name: keeps decisions of different models apart


@POLICIES.register("replay", ReplayConfig)
class ReplayPolicy(Policy):
    name = "replay"

    def __init__(self, config: ReplayConfig, inner: Policy | None = None, builder: PromptBuilder | None = None):
        super().__init__()
        self.config = config
        # The cache key is the prompt the inner backend would send: its scene-graph switch shapes it.
        self.builder = builder or PromptBuilder(PromptConfig(
            scene_graph=bool(config.inner_config.get("scene_graph", True))))
        self._inner = inner
        self._cache: dict[str, dict] = {}
        self.path = Path(config.path)
        self._load()

    @property
    def inner(self) -> Policy:
        if self._inner is None:
            self._inner = POLICIES.create(self.config.inner, self.config.inner_config)
            self._inner.reset(self.mission_id)
        return self._inner

    def _load(self) -> None:
        if not self.path.exists():
            return
        with self.path.open() as f:
            for n, line in enumerate(f, 1):
                line = line.strip()
                if not line:
                    continue
                try:
                    rec = json.loads(line)
                    self._cache[rec["key"]] = rec["decision"]
                except (json.JSONDecodeError, KeyError):
                    log.warning("replay cache %s: skipping unreadable line %d", self.path, n)

    def __len__(self) -> int:
        return len(self._cache)

    def prompt_config(self) -> PromptConfig:
        """The prompt the wrapped backend would send: its layout and image limits (inner_config's, else
        its provider profile's), so that a mosaic and a separate run never share decisions."""
        inner = self.config.inner_config
        if not any(k in inner for k in _LAYOUT_KEYS):
            return self.builder.config
        prof = profile(inner.get("profile", "openai"), inner.get("profile_overrides") or {})
        images = inner.get("max_images_per_prompt") or prof.max_images_per_prompt
        px = inner.get("max_image_px") or prof.max_image_px
        return replace(self.builder.config, layout=inner.get("layout", "auto"), max_images_per_prompt=images,
                       max_image_px=px, image_token_rule=prof.image_token_rule)

    def key(self, ctx: StepContext) -> str:
        """Cache key: the wrapped backend, the namespace, the prompt's layout settings and the prompt's
        content hash (which covers the composed images)."""
        cfg = self.prompt_config()
        digest = self.builder.build(ctx, cfg).digest()
        key = f"{self.config.inner}\x00{self.config.namespace}\x00{digest}"
        if any(k in self.config.inner_config for k in _LAYOUT_KEYS):
            # Only then: caches recorded before layouts existed keep their keys.
            layout = json.dumps({k: self.config.inner_config.get(k) for k in _LAYOUT_KEYS}, sort_keys=True)
            key = f"{key}\x00{layout}"
        h = hashlib.sha256(key.encode())
        return h.hexdigest()

    def reset(self, mission_id: str) -> None:
        super().reset(mission_id)
        if self._inner is not None:
            self._inner.reset(mission_id)

    def decide(self, ctx: StepContext) -> Decision:
        key = self.key(ctx)
        hit = self._cache.get(key)
        if hit is not None:
            decision = Decision.model_validate(hit)
            # Recorded costs were paid once; a replayed decision is free.
            decision = decision.model_copy(
                update={"backend": f"replay:{hit.get('backend', self.config.inner)}", "prompt_tokens": 0,
                        "completion_tokens": 0, "cost_usd": 0.0}
            )
            self.usage.cache_hits += 1
            ctx.candidate(decision.candidate_index)  # the cached index must exist in this context
            return decision
        if self.config.mode == "read_only":
            raise ReplayMissError(f"no cached decision for step {ctx.step} of mission {ctx.mission_id!r}")
        decision = self.inner.decide(ctx)
        self._append(key, decision)
        self.usage.calls += 1
        self.usage.prompt_tokens += decision.prompt_tokens
        self.usage.completion_tokens += decision.completion_tokens
        self.usage.cost_usd += decision.cost_usd
        self.usage.fallbacks += int(decision.fallback)
        return decision

    def _append(self, key: str, decision: Decision) -> None:
        rec = {"key": key, "decision": decision.model_dump(mode="json")}
        self._cache[key] = rec["decision"]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as f:
            f.write(json.dumps(rec) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def close(self) -> None:
        if self._inner is not None:
            self._inner.close()
