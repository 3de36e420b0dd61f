"""MLLM policy over any OpenAI-compatible chat-completions endpoint (OpenAI, vLLM, SGLang, Ollama ...).

One step: build the prompt within the server's limits (its provider profile: image cap, context window,
parameter set; see :mod:`.providers` and :mod:`.budget`), call the endpoint, parse the answer; an invalid
answer gets exactly one corrective re-ask, then the safe fallback (the heuristic policy by default, or
stop). Errors by kind: timeouts, 429 and 5xx are retried with backoff; a context-overflow answer gets one
retry with a prompt compressed to half its size; any other refusal (400/422 ...) ends the mission with the
server's message, since a wrong request stays wrong. Tokens and cost are counted per mission.
"""

from __future__ import annotations

import email.utils
import json
import logging
import os
import random
import time
from dataclasses import replace
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from shared.pricing import PriceTable
from shared.registry import BackendConfig
from shared.schemas import Decision, UsageData

from .budget import fit_prompt
from .context import StepContext
from .errors import AnswerError, PolicyBackendError
from .layout import Layout
from .policy import POLICIES, Policy
from .prompt import Prompt, PromptBuilder, PromptConfig, corrective_message, parse_answer, split_thinking
from .providers import (
    PROFILES,
    ContextOverflowError,
    ProviderProfile,
    RequestRejectedError,
    is_context_overflow,
    profile,
    read_context_window,
)
from .tokens import prompt_tokens

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
    # The server kind (providers.PROFILES) and any field of it changed for this deployment, e.g.
    # {"max_images_per_prompt": 8, "context_window_tokens": 16384} for vLLM started with those limits.
    profile: str = "openai"
    profile_overrides: dict = Field(default_factory=dict)
    # auto: separate images while they fit the image cap, else numbered mosaics (see core/layout.py).
    layout: Layout = "auto"
    max_images_per_prompt: int | None = Field(None, ge=1, le=10_000)  # None: the profile's
    max_image_px: int | None = Field(None, ge=16, le=8192)  # None: the profile's
    context_window_tokens: int | None = Field(None, ge=512, le=10_000_000)  # None: the profile's / server's
    json_mode: bool = False  # send response_format json_object where the profile supports it
    seed: int | None = Field(None, ge=0, le=2**31 - 1)  # sent where the profile supports it

    @field_validator("profile")
    @classmethod
    def _profile(cls, v):
        if v not in PROFILES:
            raise ValueError(f"unknown provider profile {v!r}; have {sorted(PROFILES)}")
        return v
    # The map's scene graph as text in the prompt (issue 32's ablation switch, as the heuristic's).
    scene_graph: bool = True
    scene_graph_max_chars: int = Field(4000, ge=200, le=100_000)

    @field_validator("base_url")
    @classmethod
    def _url(cls, v):
        if v is not None and not v.startswith(("http://", "https://")):
            raise ValueError(f"base_url must be http(s), got {v!r}")
        return v


def server_message(exc: Exception) -> str:
    """The server's own error text: OpenAI nests it as ``{"error": {"message"}}`` (the SDK unwraps that
    into ``body``), vLLM sends ``{"object": "error", "message"}``."""
    body = getattr(exc, "body", None)
    if isinstance(body, dict):
        inner = body.get("error", body)
        if isinstance(inner, dict) and isinstance(inner.get("message"), str):
            return inner["message"]
        if isinstance(inner, str):
            return inner
    return str(exc)


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
        self._key = key
        self.profile: ProviderProfile = profile(config.profile, config.profile_overrides)
        self._window: int | None = None
        self._window_read = False

    def prompt_config(self) -> PromptConfig:
        """The builder's config with this server's layout and image limits."""
        cfg, prof = self.config, self.profile
        images = cfg.max_images_per_prompt if cfg.max_images_per_prompt is not None else prof.max_images_per_prompt
        px = cfg.max_image_px if cfg.max_image_px is not None else prof.max_image_px
        return replace(self.builder.config, layout=cfg.layout, max_images_per_prompt=images, max_image_px=px,
                       image_token_rule=prof.image_token_rule)

    def context_window(self) -> int | None:
        """The window: the config's, else what the server reports (profiles that say it does), else the
        profile's default. Read once per policy."""
        if self.config.context_window_tokens is not None:
            return self.config.context_window_tokens
        if not self._window_read:
            self._window_read = True
            if self.profile.context_from_models and self.config.base_url:
                self._window = read_context_window(self.config.base_url, self.config.model, self._key,
                                                   min(5.0, self.config.timeout_s))
            if self._window is None:
                self._window = self.profile.context_window_tokens
        return self._window

    def budget_tokens(self) -> int | None:
        window = self.context_window()
        if window is None:
            return None
        reserve = self.config.max_completion_tokens or self.profile.reserve_output_tokens
        return max(1, window - reserve)

    def count_tokens(self, prompt: Prompt) -> int:
        return prompt_tokens(prompt, self._detail() or "auto", self.profile.image_token_rule)

    def _detail(self) -> str | None:
        return self.config.image_detail if self.profile.supports_detail else None

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

    def request_kwargs(self, messages: list[dict]) -> dict:
        """The request body's fields: only those the profile says the server takes."""
        cfg, prof = self.config, self.profile
        kwargs: dict = {"model": cfg.model, "messages": messages}
        if cfg.temperature is not None:
            kwargs["temperature"] = cfg.temperature
        if cfg.reasoning_effort is not None:
            kwargs["reasoning_effort"] = cfg.reasoning_effort
        if cfg.max_completion_tokens is not None:
            kwargs[prof.token_limit_param] = cfg.max_completion_tokens
        if cfg.json_mode and prof.supports_response_format:
            kwargs["response_format"] = {"type": "json_object"}
        if cfg.seed is not None and prof.supports_seed:
            kwargs["seed"] = cfg.seed
        return kwargs

    def _complete(self, messages: list[dict], usage: UsageData) -> tuple[str, str]:
        """(answer text, thinking) of one request."""
        cfg = self.config
        kwargs = self.request_kwargs(messages)
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
            except _openai().APIStatusError as exc:  # 4xx: the request is wrong, retrying will not help
                message = server_message(exc)
                status = getattr(exc, "status_code", 0)
                if status == 413 or is_context_overflow(message):
                    raise ContextOverflowError(f"{cfg.model}: HTTP {status}: {message}") from exc
                raise RequestRejectedError(f"{cfg.model}: HTTP {status}: {message}") from exc
            except _openai().APIError as exc:  # an unreadable response and the like
                raise PolicyBackendError(f"{cfg.model}: {type(exc).__name__}: {exc}") from exc
            usage.calls += 1
            if resp.usage is not None:
                pin, pout = self._price()
                n_in, n_out = resp.usage.prompt_tokens or 0, resp.usage.completion_tokens or 0
                usage.prompt_tokens += n_in
                usage.completion_tokens += n_out
                usage.cost_usd += (n_in * pin + n_out * pout) / 1e6
            if not resp.choices:
                return "", ""
            message = resp.choices[0].message
            text, thinking = split_thinking(message.content or "")
            # vLLM/SGLang reasoning parsers return the thinking beside the content.
            extra = getattr(message, "reasoning_content", None) or (message.model_extra or {}).get("reasoning_content")
            if isinstance(extra, str) and extra.strip():
                thinking = (extra.strip() + "\n" + thinking).strip()
            return text, thinking
        raise AssertionError("unreachable")

    # --- one step ------------------------------------------------------------------------------------

    def decide(self, ctx: StepContext) -> Decision:
        cfg = self.config
        budget = self.budget_tokens()
        prompt, n_tokens, notes = fit_prompt(self.builder, ctx, self.prompt_config(), self.count_tokens, budget)
        valid = prompt.candidate_indices
        step_usage = UsageData()
        answers: list[str] = []
        thinking: list[str] = []
        error: Exception | None = None
        try:
            try:
                decision = self._ask(ctx, prompt, valid, step_usage, answers, thinking, notes)
            except ContextOverflowError as exc:
                # The server counts differently from us (its tokenizer, its image rule): one retry with
                # a prompt compressed to half of what it refused, then the refusal stands.
                log.warning("step %d: %s; retrying once with a compressed prompt", ctx.step, exc)
                refused = n_tokens
                prompt, n_tokens, notes2 = fit_prompt(self.builder, ctx, self.prompt_config(), self.count_tokens,
                                                      max(1, refused // 2))
                notes = notes + [f"server refused {refused} counted tokens as too long: retried"] + notes2
                decision = self._ask(ctx, prompt, valid, step_usage, answers, thinking, notes)
            if decision is not None:
                self._save(prompt, ctx, answers, decision)
                return decision
            error = self._last_answer_error
        except RequestRejectedError:
            self.usage.add(step_usage)
            raise  # a wrong request ends the mission with the server's message, never a fallback
        except PolicyBackendError as exc:
            if self.config.on_error == "raise":
                self.usage.add(step_usage)
                raise
            error = exc
            log.error("step %d: %s; falling back to %s", ctx.step, exc, self.config.fallback)
        decision = self._fallback_decision(ctx, error, step_usage)
        decision = decision.model_copy(update=self._record_fields(notes, thinking, prompt))
        self._save(prompt, ctx, answers, decision)
        return decision

    def _record_fields(self, notes: list[str], thinking: list[str], prompt: Prompt) -> dict:
        notes = [f"layout {prompt.meta.get('layout')}, {len(prompt.images())} images"] + notes
        return {"prompt_notes": "; ".join(notes)[:2000], "thinking": "\n---\n".join(t for t in thinking if t)[:20_000]}

    def _ask(self, ctx: StepContext, prompt: Prompt, valid: list[int], step_usage: UsageData, answers: list[str],
             thinking: list[str], notes: list[str]) -> Decision | None:
        """The answer, then one corrective re-ask; None when both were invalid."""
        cfg = self.config
        messages = prompt.to_openai_messages(cfg.image_format, cfg.jpeg_quality, self._detail())
        self._last_answer_error: Exception | None = None
        for attempt in range(2):
            text, thought = self._complete(messages, step_usage)
            answers.append(text)
            thinking.append(thought)
            try:
                index, reasoning = parse_answer(text, valid)
            except AnswerError as exc:
                self._last_answer_error = exc
                log.warning("step %d: invalid answer (%s)%s", ctx.step, exc, "; re-asking" if attempt == 0 else "")
                if attempt == 0:
                    step_usage.reasks += 1
                    messages = messages + [
                        {"role": "assistant", "content": text},
                        {"role": "user", "content": corrective_message(exc, valid)},
                    ]
                continue
            return self._decision(ctx, index, reasoning, **self._usage_fields(step_usage),
                                  **self._record_fields(notes, thinking, prompt))
        return None

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
