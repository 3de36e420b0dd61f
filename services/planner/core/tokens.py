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

from .prompt import Prompt, PromptImage

MESSAGE_OVERHEAD_TOKENS = 3
REPLY_PRIMING_TOKENS = 3
_PIECE = re.compile(r"[A-Za-z0-9]+|[^\sA-Za-z0-9]")


def text_tokens(text: str) -> int:
    """Approximate BPE tokens of ``text`` (see the module docstring)."""
    return sum(math.ceil(len(p) / 4) if p[0].isalnum() else 1 for p in _PIECE.findall(text))


def image_tokens(width_px: int, height_px: int, detail: str = "auto") -> int:
    """OpenAI's image cost: 85 base tokens + 170 per 512 px tile after scaling (``low``: 85)."""
    if detail == "low":
        return 85
    w, h = float(width_px), float(height_px)
    if max(w, h) > 2048:
        s = 2048 / max(w, h)
        w, h = w * s, h * s
    if min(w, h) > 768:
        s = 768 / min(w, h)
        w, h = w * s, h * s
    return 85 + 170 * math.ceil(w / 512) * math.ceil(h / 512)


def qwen_patch_tokens(width_px: int, height_px: int, detail: str = "auto") -> int:
    """Qwen2.5-VL's processor (``smart_resize``, 28 px merged patches, default pixel bounds) + 2."""
    factor, min_px, max_px = 28, 56 * 56, 12845056
    h = max(factor, round(height_px / factor) * factor)
    w = max(factor, round(width_px / factor) * factor)
    if h * w > max_px:
        beta = math.sqrt(height_px * width_px / max_px)
        h = max(factor, math.floor(height_px / beta / factor) * factor)
        w = max(factor, math.floor(width_px / beta / factor) * factor)
    elif h * w < min_px:
        beta = math.sqrt(min_px / (height_px * width_px))
        h = math.ceil(height_px * beta / factor) * factor
        w = math.ceil(width_px * beta / factor) * factor
    return (h // factor) * (w // factor) + 2


def gemini_tile_tokens(width_px: int, height_px: int, detail: str = "auto") -> int:
    """Gemini: 258 tokens up to 384 px on both sides, else 258 per 768 px tile."""
    if width_px <= 384 and height_px <= 384:
        return 258
    return 258 * math.ceil(width_px / 768) * math.ceil(height_px / 768)


IMAGE_TOKEN_RULES = {
    "openai_tiles": image_tokens,
    "qwen_patches": qwen_patch_tokens,
    "gemini_tiles": gemini_tile_tokens,
}


def image_tokens_by(rule: str, width_px: int, height_px: int, detail: str = "auto") -> int:
    try:
        fn = IMAGE_TOKEN_RULES[rule]
    except KeyError:
        raise ValueError(f"unknown image-token rule {rule!r}; have {sorted(IMAGE_TOKEN_RULES)}") from None
    return fn(width_px, height_px, detail)


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
