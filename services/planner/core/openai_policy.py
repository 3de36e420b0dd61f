"""MLLM policy over any OpenAI-compatible chat-completions endpoint (OpenAI, vLLM, SGLang, Ollama ...).

One step: build the prompt, call the endpoint (timeouts, retries with exponential backoff on transient
errors), parse the answer; an invalid answer gets exactly one corrective re-ask, then the safe fallback
(the heuristic policy by default, or stop). Tokens and cost are counted per mission.
"""

from __future__ import annotations

import email.utils
import json
import logging
import os
import random
import time
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from shared.pricing import PriceTable
from shared.registry import BackendConfig
from shared.schemas import Decision, UsageData

from .context import StepContext
from .errors import AnswerError, PolicyBackendError
from .policy import POLICIES, Policy
from .prompt import PromptBuilder, PromptConfig, corrective_message, parse_answer

log = logging.getLogger(__name__)

# Prices come from the table in shared/pricing.py (the evaluation's estimates use the same one)
# unless the config gives them. Unknown models cost 0.


class OpenAIConfig(BackendConfig):
    """An OpenAI-compatible endpoint. The key comes from ``api_key`` or the ``api_key_env`` variable."""

    model: str = "gpt-5.1"
    base_url: str | None = None  # None: api.openai.com (or OPENAI_BASE_URL)
    api_key: str | None = Field(default=None, repr=False)
    api_key_env: str = "OPENAI_API_KEY"
    temperature: float | None = None  # None: not sent (reasoning models accept only the default)
    reasoning_effort: Literal["none", "minimal", "low", "medium", "high"] | None = None
    max_completion_tokens: int | None = None
    timeout_s: float = Field(60.0, gt=0)
    retries: int = Field(2, ge=0, le=10)
    backoff_initial_s: float = Field(1.0, ge=0)
    backoff_max_s: float = Field(20.0, ge=0)
    # A 429's Retry-After is waited (at least the backoff, at most this): the server knows its window.
    retry_after_max_s: float = Field(60.0, ge=0)
    image_format: Literal["png", "jpeg"] = "jpeg"
    jpeg_quality: int = Field(90, ge=10, le=100)
    image_detail: Literal["auto", "low", "high"] = "auto"
    price_input_per_1m_usd: float | None = None
    price_output_per_1m_usd: float | None = None
    fallback: Literal["heuristic", "stop"] = "heuristic"
    on_error: Literal["fallback", "raise"] = "fallback"  # after retries are exhausted
    save_prompts_dir: str | None = None  # save every step's prompt, answer and re-ask here
    # The map's scene graph as text in the prompt (issue 32's ablation switch, as the heuristic's).
    scene_graph: bool = True
    scene_graph_max_chars: int = Field(4000, ge=200, le=100_000)

    @field_validator("base_url")
    @classmethod
    def _url(cls, v):
        if v is not None and not v.startswith(("http://", "https://")):
            raise ValueError(f"base_url must be http(s), got {v!r}")
        return v


def _openai():
    # Imported on first use, not with the planner: the SDK costs ~2.6 s at every planner start (measured
    # under load with -X importtime), and the default policy is the heuristic.
    import openai

    return openai


def _transient() -> tuple[type[Exception], ...]:
    o = _openai()
    return (o.APITimeoutError, o.APIConnectionError, o.RateLimitError, o.InternalServerError)


def retry_after_s(exc: Exception) -> float | None:
    """The server's ``Retry-After`` (seconds or an HTTP date) or ``retry-after-ms``, if it sent one."""
    response = getattr(exc, "response", None)
    headers = getattr(response, "headers", None)
    if headers is None:
        return None
    ms = headers.get("retry-after-ms")
    try:
        if ms is not None:
            return max(0.0, float(ms) / 1000.0)
        value = headers.get("retry-after")
        if value is None:
            return None
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(headers.get("retry-after"))
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


@POLICIES.register("openai", OpenAIConfig)
class OpenAIPolicy(Policy):
    name = "openai"

    def __init__(self, config: OpenAIConfig, builder: PromptBuilder | None = None):
        super().__init__()
        self.config = config
        self.builder = builder or PromptBuilder(PromptConfig(scene_graph=config.scene_graph,
                                                             scene_graph_max_chars=config.scene_graph_max_chars))
        key = config.api_key or os.environ.get(config.api_key_env)
        if not key:
            if config.base_url is None:
                raise PolicyBackendError(f"no API key: set {config.api_key_env} or api_key in the policy config")
            key = "not-needed"  # local servers (vLLM, Ollama) usually take any key
        # Retries are ours (typed, logged, with jittered backoff), so the SDK's are off.
        self._client = _openai().OpenAI(api_key=key, base_url=config.base_url, timeout=config.timeout_s, max_retries=0)
        self._fallback: Policy | None = None
        self._rng = random.Random(0)

    def reset(self, mission_id: str) -> None:
        super().reset(mission_id)
        if self._fallback is not None:
            self._fallback.reset(mission_id)

    def close(self) -> None:
        self._client.close()

    # --- one request ---------------------------------------------------------------------------------

    def _price(self) -> tuple[float, float]:
        base = PriceTable().price(self.config.model)
        pin = self.config.price_input_per_1m_usd
        pout = self.config.price_output_per_1m_usd
        return (base.input_per_1m_usd if pin is None else pin, base.output_per_1m_usd if pout is None else pout)

    def _complete(self, messages: list[dict], usage: UsageData) -> str:
        cfg = self.config
        kwargs: dict = {"model": cfg.model, "messages": messages}
        if cfg.temperature is not None:
            kwargs["temperature"] = cfg.temperature
        if cfg.reasoning_effort is not None:
            kwargs["reasoning_effort"] = cfg.reasoning_effort
        if cfg.max_completion_tokens is not None:
            kwargs["max_completion_tokens"] = cfg.max_completion_tokens
        delay = cfg.backoff_initial_s
        for attempt in range(cfg.retries + 1):
            try:
                resp = self._client.chat.completions.create(**kwargs)
            except _transient() as exc:
                if attempt >= cfg.retries:
                    raise PolicyBackendError(
                        f"{cfg.model}: {type(exc).__name__} after {attempt + 1} attempts: {exc}"
                    ) from exc
                sleep = min(delay, cfg.backoff_max_s) * (0.5 + self._rng.random())
                hinted = retry_after_s(exc)
                if hinted is not None:
                    sleep = max(sleep, min(hinted, cfg.retry_after_max_s))
                log.warning(
                    "%s: %s, retrying in %.2f s (%d/%d)", cfg.model, type(exc).__name__, sleep, attempt + 1, cfg.retries
                )
                time.sleep(sleep)
                delay *= 2.0
                continue
            except _openai().APIError as exc:  # 4xx and the like: retrying will not help
                raise PolicyBackendError(f"{cfg.model}: {type(exc).__name__}: {exc}") from exc
            usage.calls += 1
            if resp.usage is not None:
                pin, pout = self._price()
                n_in, n_out = resp.usage.prompt_tokens or 0, resp.usage.completion_tokens or 0
                usage.prompt_tokens += n_in
                usage.completion_tokens += n_out
                usage.cost_usd += (n_in * pin + n_out * pout) / 1e6
            if not resp.choices:
                return ""
            return resp.choices[0].message.content or ""
        raise AssertionError("unreachable")

    # --- one step ------------------------------------------------------------------------------------

    def decide(self, ctx: StepContext) -> Decision:
        prompt = self.builder.build(ctx)
        valid = prompt.candidate_indices
        cfg = self.config
        messages = prompt.to_openai_messages(cfg.image_format, cfg.jpeg_quality, cfg.image_detail)
        step_usage = UsageData()
        answers: list[str] = []
        error: Exception | None = None
        try:
            for attempt in range(2):  # the answer, then one corrective re-ask
                text = self._complete(messages, step_usage)
                answers.append(text)
                try:
                    index, reasoning = parse_answer(text, valid)
                except AnswerError as exc:
                    error = exc
                    log.warning("step %d: invalid answer (%s)%s", ctx.step, exc, "; re-asking" if attempt == 0 else "")
                    if attempt == 0:
                        step_usage.reasks += 1
                        messages = messages + [
                            {"role": "assistant", "content": text},
                            {"role": "user", "content": corrective_message(exc, valid)},
                        ]
                    continue
                decision = self._decision(ctx, index, reasoning, **self._usage_fields(step_usage))
                self._save(prompt, ctx, answers, decision)
                return decision
        except PolicyBackendError as exc:
            if self.config.on_error == "raise":
                self.usage.add(step_usage)
                raise
            error = exc
            log.error("step %d: %s; falling back to %s", ctx.step, exc, self.config.fallback)
        decision = self._fallback_decision(ctx, error, step_usage)
        self._save(prompt, ctx, answers, decision)
        return decision

    def _usage_fields(self, step_usage: UsageData) -> dict:
        self.usage.add(step_usage)
        return {
            "prompt_tokens": step_usage.prompt_tokens,
            "completion_tokens": step_usage.completion_tokens,
            "cost_usd": step_usage.cost_usd,
            "backend": f"openai:{self.config.model}",
        }

    def _fallback_decision(self, ctx: StepContext, error: Exception | None, step_usage: UsageData) -> Decision:
        step_usage.fallbacks += 1
        fields = self._usage_fields(step_usage)
        reason = f"fallback ({self.config.fallback}) after: {error}"
        stop = ctx.stop_candidate
        if self.config.fallback == "heuristic":
            if self._fallback is None:
                self._fallback = POLICIES.create("heuristic")
                self._fallback.reset(self.mission_id)
            d = self._fallback.decide(ctx)
            return d.model_copy(update={**fields, "fallback": True, "reasoning": f"{reason}; {d.reasoning}"})
        index = stop.index if stop is not None else ctx.candidates[0].index
        return self._decision(ctx, index, reason, fallback=True, **fields)

    def _save(self, prompt, ctx: StepContext, answers: list[str], decision: Decision) -> None:
        if not self.config.save_prompts_dir:
            return
        mission = ctx.mission_id or self.mission_id or "mission"
        folder = prompt.save(Path(self.config.save_prompts_dir) / mission / f"step_{ctx.step:03d}")
        (folder / "answer.json").write_text(
            json.dumps({"answers": answers, "decision": decision.model_dump(mode="json")}, indent=2)
        )
