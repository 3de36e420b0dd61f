"""Image-token rules by server (see :mod:`.tokens` for the rules' sources); no planner imports, so the
prompt builder can size its mosaics by them."""

from __future__ import annotations

import math


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
