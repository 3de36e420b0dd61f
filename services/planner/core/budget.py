"""The context budget: a step prompt that fits the server's window, compressed in a fixed order.

Counted before sending (text + images by the profile's image-token rule). Over budget, the prompt gives up,
in order: history frames (halved each time; their action text stays, which is most of what the history
says), the separate layout (a mosaic packs views into fewer billed tiles), then image size (halved down to
:data:`MIN_IMAGE_PX`). What was given up is returned as notes for the step record. When nothing is left to
give, :class:`ContextBudgetError`: the request is never sent, because the server would refuse it (or,
like Ollama, silently cut the instruction off).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from .context import StepContext
from .prompt import Prompt, PromptBuilder, PromptConfig
from .providers import ContextBudgetError

MIN_IMAGE_PX = 64  # below this a room view shows nothing a model can use


def fit_prompt(builder: PromptBuilder, ctx: StepContext, cfg: PromptConfig, count: Callable[[Prompt], int],
               budget_tokens: int | None) -> tuple[Prompt, int, list[str]]:
    """(prompt, its token count, notes). ``budget_tokens`` None: no limit."""
    prompt = builder.build(ctx, cfg)
    n = count(prompt)
    notes: list[str] = []
    layout = prompt.meta.get("layout")
    if cfg.layout == "auto" and layout == "mosaic":
        notes.append(f"layout mosaic ({builder.separate_image_count(ctx, cfg)} separate images > "
                     f"limit {cfg.max_images_per_prompt})")
    if budget_tokens is None or n <= budget_tokens:
        return prompt, n, notes
    first_n, first = n, cfg
    items = min(len(ctx.history), cfg.max_history_items)
    frames = items if cfg.max_history_frames is None else min(items, cfg.max_history_frames)
    while n > budget_tokens:
        if frames > 0:
            frames //= 2
            cfg = replace(cfg, max_history_frames=frames)
        elif builder.resolve_layout(ctx, cfg) == "separate" and cfg.layout == "auto":
            cfg = replace(cfg, layout="mosaic")
        elif cfg.image_px > MIN_IMAGE_PX:
            cfg = replace(cfg, image_px=max(MIN_IMAGE_PX, cfg.image_px // 2))
        else:
            raise ContextBudgetError(
                f"the step prompt needs {n} tokens with every compression applied (no history frames, "
                f"{cfg.image_px} px images), over the budget of {budget_tokens}: not sent; raise the "
                f"server's context window or lower the candidates per step")
        prompt = builder.build(ctx, cfg)
        n = count(prompt)
    if cfg.max_history_frames != first.max_history_frames:
        notes.append(f"history frames {items}->{cfg.max_history_frames}")
    if cfg.layout != first.layout:
        notes.append("layout separate->mosaic")
    if cfg.image_px != first.image_px:
        notes.append(f"image px {first.image_px}->{cfg.image_px}")
    notes.append(f"prompt {first_n}->{n} tokens (budget {budget_tokens})")
    return prompt, n, notes
