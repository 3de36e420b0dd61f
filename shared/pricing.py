"""LLM prices per model, as data: the default table below, overridable by a JSON or TOML file.

A table file maps a model name to its prices in USD per 1M tokens::

    # prices.toml                               // prices.json
    ["gpt-5.1"]                                 {"gpt-5.1": {"input_per_1m_usd": 1.25,
    input_per_1m_usd = 1.25                                  "output_per_1m_usd": 10.0}}
    output_per_1m_usd = 10.0

Entries of a file replace (or add to) the defaults. A dated snapshot (``gpt-4o-2024-08-06``) is priced as
its family (``gpt-4o``); an unknown model costs 0, which the ledger reports as unpriced. The planner
prices its calls with this table and the evaluation estimates runs with it, so both agree.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError


class ModelPrice(BaseModel):
    model_config = ConfigDict(extra="forbid")

    input_per_1m_usd: float = Field(ge=0.0, le=10_000.0, allow_inf_nan=False)
    output_per_1m_usd: float = Field(ge=0.0, le=10_000.0, allow_inf_nan=False)

    def cost_usd(self, prompt_tokens: int, completion_tokens: int) -> float:
        return (prompt_tokens * self.input_per_1m_usd + completion_tokens * self.output_per_1m_usd) / 1e6


# List prices (USD / 1M tokens, standard tier) as published by OpenAI at the time of writing.
DEFAULT_PRICES: dict[str, ModelPrice] = {
    name: ModelPrice(input_per_1m_usd=i, output_per_1m_usd=o) for name, (i, o) in {
        "gpt-5.1": (1.25, 10.0),
        "gpt-5": (1.25, 10.0),
        "gpt-5-mini": (0.25, 2.0),
        "gpt-4o": (2.5, 10.0),
        "gpt-4o-mini": (0.15, 0.6),
        "gpt-4.1": (2.0, 8.0),
    }.items()
}

FREE = ModelPrice(input_per_1m_usd=0.0, output_per_1m_usd=0.0)


class PriceTableError(ValueError):
    """A price table file that cannot be read."""


class PriceTable:
    """Model name -> :class:`ModelPrice`."""

    def __init__(self, prices: dict[str, ModelPrice] | None = None):
        self.prices = dict(DEFAULT_PRICES if prices is None else prices)

    @classmethod
    def load(cls, path: Path | str | None = None) -> PriceTable:
        """The defaults, with ``path``'s entries (JSON, or TOML by its ``.toml`` suffix) on top."""
        table = cls()
        if path is None:
            return table
        path = Path(path)
        try:
            raw = tomllib.loads(path.read_text()) if path.suffix == ".toml" else json.loads(path.read_text())
            if not isinstance(raw, dict):
                raise ValueError("the top level must map model names to prices")
            table.prices.update({str(k): ModelPrice.model_validate(v) for k, v in raw.items()})
        except (OSError, ValueError, ValidationError, tomllib.TOMLDecodeError) as exc:
            raise PriceTableError(f"{path}: not a price table ({exc})") from None
        return table

    def lookup(self, model: str) -> ModelPrice | None:
        if model in self.prices:
            return self.prices[model]
        # The longest family name that the model extends ("gpt-5-mini-2025..." is gpt-5-mini, not gpt-5).
        fam = [m for m in self.prices if model.startswith(m + "-")]
        return self.prices[max(fam, key=len)] if fam else None

    def price(self, model: str) -> ModelPrice:
        return self.lookup(model) or FREE
