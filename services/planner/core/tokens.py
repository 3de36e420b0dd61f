"""Token counts of chat prompts without a tokenizer download.

tiktoken needs its BPE files fetched at first use (no network on evaluation hosts), so text is counted
with a deterministic approximation of the o200k/cl100k tokenizers: a run of letters and digits of n
characters counts ceil(n / 4) tokens, every other non-space character one token; each message adds 3 and
the reply's priming 3 (the OpenAI cookbook's chat overhead). Images follow OpenAI's published tile rule:
``detail=low`` costs 85; otherwise the image is scaled to fit 2048 px, its short side to 768 px, and costs
85 + 170 per 512 px tile. On English prompts the text count is within ~15 % of tiktoken's; what matters
for estimates and the stand-in is that it is exact for images (most of a VLN prompt) and scales with text.

Other servers count images differently, so the rule is named (:data:`IMAGE_TOKEN_RULES`) and a provider
profile picks one: ``openai_tiles`` (above), ``qwen_patches`` (Qwen2-VL/2.5-VL behind vLLM, SGLang or
Ollama: the image is resized to multiples of 28 px within [56^2, 12845056] pixels and every 28x28 block
is one token, plus the vision start/end tokens) and ``gemini_tiles`` (258 tokens for an image of at most
384 px on both sides, else 258 per 768 px tile).
"""

from __future__ import annotations

import base64
import math
import re

import cv2
import numpy as np

from .image_tokens import IMAGE_TOKEN_RULES, gemini_tile_tokens, image_tokens, image_tokens_by, qwen_patch_tokens
from .prompt import Prompt, PromptImage

__all__ = ["IMAGE_TOKEN_RULES", "data_url_size", "gemini_tile_tokens", "image_tokens", "image_tokens_by",
           "message_tokens", "prompt_tokens", "qwen_patch_tokens", "text_tokens"]

MESSAGE_OVERHEAD_TOKENS = 3
REPLY_PRIMING_TOKENS = 3
_PIECE = re.compile(r"[A-Za-z0-9]+|[^\sA-Za-z0-9]")


def text_tokens(text: str) -> int:
    """Approximate BPE tokens of ``text`` (see the module docstring)."""
    return sum(math.ceil(len(p) / 4) if p[0].isalnum() else 1 for p in _PIECE.findall(text))


def data_url_size(url: str) -> tuple[int, int]:
    """(width, height) of a ``data:image/...;base64,`` URL; a remote URL counts as one 512 px tile."""
    if not url.startswith("data:") or "," not in url:
        return 512, 512
    img = cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("an image_url carries no decodable image")
    return img.shape[1], img.shape[0]


def message_tokens(messages: list[dict], rule: str = "openai_tiles") -> int:
    """Prompt tokens of chat-completions ``messages`` (text parts and ``image_url`` parts)."""
    total = REPLY_PRIMING_TOKENS
    for m in messages:
        total += MESSAGE_OVERHEAD_TOKENS
        content = m.get("content")
        if isinstance(content, str):
            total += text_tokens(content)
            continue
        for part in content or []:
            if part.get("type") == "text":
                total += text_tokens(part.get("text", ""))
            elif part.get("type") == "image_url":
                img = part.get("image_url") or {}
                total += image_tokens_by(rule, *data_url_size(img.get("url", "")), img.get("detail", "auto"))
    return total


def prompt_tokens(prompt: Prompt, detail: str = "auto", rule: str = "openai_tiles") -> int:
    """Prompt tokens of a :class:`Prompt` as sent (the same count as :func:`message_tokens` of its
    messages, without encoding any image)."""
    total = REPLY_PRIMING_TOKENS + 2 * MESSAGE_OVERHEAD_TOKENS + text_tokens(prompt.system)
    text = []
    for p in prompt.parts:
        if isinstance(p, PromptImage):
            total += text_tokens("".join(text)) + image_tokens_by(rule, p.rgb.shape[1], p.rgb.shape[0], detail)
            text = []
        else:
            text.append(p)
    return total + text_tokens("".join(text))
