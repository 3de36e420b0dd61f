"""Provider profiles as data: what each OpenAI-compatible server accepts and how it counts.

The openai policy speaks one protocol to many servers, which differ in what they refuse: vLLM caps the
images of a request (``--limit-mm-per-prompt``, default 1 image) and its context (``--max-model-len``),
Ollama's window is its ``num_ctx`` (it truncates the prompt silently, so the planner must not overflow it),
reasoning models want ``max_completion_tokens`` where older servers read ``max_tokens``, and only some
accept ``response_format``, image ``detail`` or ``seed``. A profile records these; it is chosen by name
and any field can be overridden in the policy config (``profile_overrides``). Where a server reports its
window in ``/v1/models`` (vLLM and SGLang: ``max_model_len``; LM Studio and llama.cpp-style servers:
``max_context_length`` / ``context_length``) the profile says so and the policy reads it at start.
"""

from __future__ import annotations

import json
import logging
import urllib.error
import urllib.request
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .errors import PolicyBackendError
from .tokens import IMAGE_TOKEN_RULES

log = logging.getLogger(__name__)

# Keys under which servers report a model's context window in /v1/models, in the order tried.
CONTEXT_KEYS = ("max_model_len", "max_context_length", "context_length", "context_window")


class ProviderProfile(BaseModel):
    """What one kind of server accepts. ``None`` limits are unknown (no check)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    max_images_per_prompt: int | None = Field(None, ge=1, le=10_000)
    context_window_tokens: int | None = Field(None, ge=512, le=10_000_000)
    context_from_models: bool = False  # read the window from GET {base_url}/models when reported
    token_limit_param: Literal["max_tokens", "max_completion_tokens"] = "max_tokens"
    supports_response_format: bool = False
    supports_detail: bool = False
    supports_seed: bool = False
    image_token_rule: str = "openai_tiles"
    max_image_px: int | None = Field(None, ge=16, le=8192)  # images above are resized by the server anyway
    # Kept free for the answer when no max completion is configured: the budget must leave room to reply.
    reserve_output_tokens: int = Field(512, ge=16, le=200_000)

    def model_post_init(self, _ctx: Any) -> None:
        if self.image_token_rule not in IMAGE_TOKEN_RULES:
            raise ValueError(f"unknown image_token_rule {self.image_token_rule!r}; have {sorted(IMAGE_TOKEN_RULES)}")


# The table. Figures are the servers' documented defaults; a deployment that raises them (vLLM with
# --limit-mm-per-prompt '{"image": 8}', Ollama with num_ctx 32768) says so in profile_overrides.
PROFILES: dict[str, dict[str, Any]] = {
    # OpenAI: 500 images per request, GPT-5.1's 400k window; reasoning models refuse max_tokens.
    "openai": dict(max_images_per_prompt=500, context_window_tokens=400_000,
                   token_limit_param="max_completion_tokens", supports_response_format=True,
                   supports_detail=True, supports_seed=True, image_token_rule="openai_tiles"),
    # Azure OpenAI deployments of the same models: a lower image cap per request (50).
    "azure-openai": dict(max_images_per_prompt=50, context_window_tokens=400_000,
                         token_limit_param="max_completion_tokens", supports_response_format=True,
                         supports_detail=True, supports_seed=True, image_token_rule="openai_tiles"),
    # vLLM: --limit-mm-per-prompt defaults to one image (vllm#13513); the window is --max-model-len,
    # reported as max_model_len by /v1/models. Guided decoding gives response_format; detail is ignored.
    "vllm": dict(max_images_per_prompt=1, context_window_tokens=32_768, context_from_models=True,
                 token_limit_param="max_tokens", supports_response_format=True, supports_detail=False,
                 supports_seed=True, image_token_rule="qwen_patches"),
    # SGLang: no per-request image cap by default; /v1/models reports max_model_len.
    "sglang": dict(max_images_per_prompt=None, context_window_tokens=32_768, context_from_models=True,
                   token_limit_param="max_tokens", supports_response_format=True, supports_detail=False,
                   supports_seed=True, image_token_rule="qwen_patches"),
    # Ollama's OpenAI compatibility: num_ctx defaults to 4096 and is not in /v1/models; a longer prompt is
    # truncated from the start without an error, so this window is a hard budget.
    "ollama": dict(max_images_per_prompt=None, context_window_tokens=4096, context_from_models=False,
                   token_limit_param="max_tokens", supports_response_format=True, supports_detail=False,
                   supports_seed=True, image_token_rule="qwen_patches"),
    # LM Studio: structured output only as json_schema, the loaded context length in its model list.
    "lmstudio": dict(max_images_per_prompt=None, context_window_tokens=4096, context_from_models=True,
                     token_limit_param="max_tokens", supports_response_format=False, supports_detail=False,
                     supports_seed=True, image_token_rule="qwen_patches"),
    # Gemini's OpenAI-compatible endpoint: 1M window, 3600 images, its own 258-token image rule.
    "gemini-openai": dict(max_images_per_prompt=3600, context_window_tokens=1_048_576,
                          token_limit_param="max_tokens", supports_response_format=True, supports_detail=False,
                          supports_seed=False, image_token_rule="gemini_tiles"),
    # Anything else: send the least, check what /v1/models tells.
    "generic": dict(max_images_per_prompt=None, context_window_tokens=None, context_from_models=True,
                    token_limit_param="max_tokens", supports_response_format=False, supports_detail=False,
                    supports_seed=False, image_token_rule="openai_tiles"),
}


def profile(name: str, overrides: dict[str, Any] | None = None) -> ProviderProfile:
    """The named profile with ``overrides`` applied (validated)."""
    if name not in PROFILES:
        raise ValueError(f"unknown provider profile {name!r}; have {sorted(PROFILES)}")
    return ProviderProfile(**{**PROFILES[name], **(overrides or {})})


def context_from_models_listing(listing: dict, model: str) -> int | None:
    """The context window a ``/v1/models`` answer reports for ``model`` (or its only model)."""
    data = listing.get("data") if isinstance(listing, dict) else None
    if not isinstance(data, list):
        return None
    entries = [d for d in data if isinstance(d, dict)]
    chosen = next((d for d in entries if d.get("id") == model), entries[0] if len(entries) == 1 else None)
    if chosen is None:
        return None
    for key in CONTEXT_KEYS:
        value = chosen.get(key)
        if isinstance(value, int) and not isinstance(value, bool) and 512 <= value <= 10_000_000:
            return value
    return None


def read_context_window(base_url: str, model: str, api_key: str | None = None, timeout_s: float = 5.0,
                        max_bytes: int = 1 << 20) -> int | None:
    """GET ``{base_url}/models`` and read the window; None when the server does not say (or is down:
    the request itself will then fail with its own error)."""
    req = urllib.request.Request(base_url.rstrip("/") + "/models",
                                 headers={"Authorization": f"Bearer {api_key}"} if api_key else {})
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:  # noqa: S310 - http(s) checked by config
            listing = json.loads(resp.read(max_bytes))
    except (urllib.error.URLError, OSError, ValueError) as exc:
        log.warning("could not read the context window from %s/models: %s", base_url, exc)
        return None
    return context_from_models_listing(listing, model)


class RequestRejectedError(PolicyBackendError):
    """The server refused the request as wrong (400/422 ...): retrying or falling back would hide a
    configuration error, so the mission ends with the server's message."""


class ContextOverflowError(RequestRejectedError):
    """The server said the prompt does not fit its context window."""


class ContextBudgetError(RequestRejectedError):
    """Even fully compressed, the prompt would not fit the window: not sent."""


# Phrases of the servers' context-overflow errors (OpenAI: code context_length_exceeded, "maximum context
# length"; vLLM: "This model's maximum context length is N tokens"; others: "prompt is too long").
_OVERFLOW_MARKERS = ("context_length_exceeded", "maximum context length", "context length", "prompt is too long",
                     "too many tokens", "exceeds the context window", "input is too long")


def is_context_overflow(message: str) -> bool:
    text = message.lower()
    return any(m in text for m in _OVERFLOW_MARKERS)
