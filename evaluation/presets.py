"""Experiment presets mirroring the paper's ablation tables, one command each.

Every preset runs the runner over the same episodes with different options (one output folder per
variant, so each variant is resumable on its own), reuses maps across variants and presets (one map
cache), and writes a comparison table (``table.md`` / ``table.csv``, with every variant's paired
bootstrap differences against the first: :mod:`evaluation.compare`) and a plot (``plot.png``).

``chunk``: the variants take turns, ``chunk`` more episodes each per round, so that a long preset
stopped at any time leaves every variant with (nearly) the same episodes done - pairs to compare.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evaluation.compare import comparison_markdown
from evaluation.errors import ConfigError
from evaluation.gateway_client import GatewayClient
from evaluation.results import COLUMNS, write_tables
from evaluation.runner import EvalRunner, Lane, SceneMapIndex, RunConfig, RunReport, SceneLoader
from libs.world import Episode, GroundTruth

log = logging.getLogger(__name__)

PLOT_METRICS = ("SR", "OSR", "SPL", "nDTW")


@dataclass(frozen=True)
class Variant:
    """One row of a preset's table: ``overrides`` applied to the base :class:`RunConfig`."""

    label: str
    overrides: dict[str, Any] = field(default_factory=dict)

    @property
    def slug(self) -> str:
        return re.sub(r"[^A-Za-z0-9_.-]+", "_", self.label).strip("_") or "variant"


@dataclass(frozen=True)
class Preset:
    name: str
    title: str
    paper: str  # what the paper reports for this comparison, printed under the table
    variants: tuple[Variant, ...]


def _policy_variants() -> tuple[Variant, ...]:
    out = [Variant("heuristic", {"policy": "heuristic"}), Variant("oracle", {"policy": "oracle"})]
    # A real MLLM only when one is configured: a run of 100 episodes is not free.
    if _llm_configured():
        out.append(Variant("openai", {"policy": "openai"}))
    return tuple(out)


def _llm_configured() -> bool:
    return bool(os.environ.get("OPENAI_API_KEY") or os.environ.get("ANT_OPENAI_BASE_URL"))


def _mllm_presets() -> tuple[Preset, ...]:
    # Issue 32's switch for the MLLM policy: the graph's text form in the prompt or not. Only with an LLM
    # configured, as the policies preset's openai row: "all" must not start a paid run by surprise.
    if not _llm_configured():
        return ()
    return (Preset("scene-graph-mllm", "With vs without the scene graph (MLLM prompt)",
                   "SpatialNav (R2R-CE): 64.0 SR / 51.1 SPL from the scene-graph prior alone; SpatialAnt 66.0 / 54.4.",
                   (Variant("openai, without scene graph", {"policy": "openai", "policy_config": {"scene_graph": False}}),
                    Variant("openai, with scene graph", {"policy": "openai", "policy_config": {"scene_graph": True}}))),)


def presets() -> dict[str, Preset]:
    """The presets by name (the policy and MLLM scene-graph presets depend on whether an LLM is configured)."""
    return {p.name: p for p in (
        Preset("cloud", "Human-curated vs agent-reconstructed point cloud",
               "Paper (R2R-CE): the agent-reconstructed cloud loses only 3.0 SR against the human-curated one.",
               (Variant("curated", {"map_source": "curated"}), Variant("reconstructed", {"map_source": "reconstructed"}))),
        Preset("anticipation", "With vs without visual anticipation",
               "Paper (R2R-CE): without anticipated views SR drops from 66 to 55.",
               (Variant("with anticipation", {"anticipation": True}),
                Variant("without anticipation", {"anticipation": False}))),
        # Issue 20's question in one paired run: does anticipation help, do the map's views (either
        # splat) reach what true views give, and what the occlusion-correct splat adds over the paper's.
        Preset("views", "Anticipated views: none vs the map's (visibility / paper splat) vs the true scene's",
               "Paper (R2R-CE): without anticipated views SR drops from 66 to 55; the true-scene views are a "
               "simulator-only control that bounds what anticipation can give the policy.",
               (Variant("without anticipation", {"anticipation": False}),
                Variant("map views, visibility splat", {"anticipation": True, "anticipation_views": "map",
                                                        "anticipation_splat_mode": "visibility"}),
                Variant("map views, paper splat", {"anticipation": True, "anticipation_views": "map",
                                                   "anticipation_splat_mode": "paper"}),
                Variant("true-scene views", {"anticipation": True, "anticipation_views": "true-scene"}))),
        Preset("hfov", "Anticipation HFOV",
               "Paper (R2R-CE): HFOV 90 deg beats 60 and 120 deg.",
               tuple(Variant(f"hfov {h}", {"anticipation": True, "anticipation_hfov_deg": float(h)})
                     for h in (60, 90, 120))),
        # Issue 32: the heuristic with the map's scene graph (grounded goal, geodesic route) against the
        # local one-step heuristic, and anticipation with a route to verify.
        Preset("scene-graph", "With vs without the scene graph (heuristic)",
               "SpatialNav (R2R-CE): 64.0 SR / 51.1 SPL from the scene-graph prior alone; SpatialAnt 66.0 / 54.4.",
               (Variant("without scene graph", {"policy_config": {"scene_graph": False}}),
                Variant("with scene graph", {"policy_config": {"scene_graph": True}}))),
        Preset("scene-graph-anticipation", "Scene graph: with vs without anticipation",
               "Paper (R2R-CE): without anticipated views SR drops from 66 to 55.",
               (Variant("scene graph, without anticipation", {"policy_config": {"scene_graph": True},
                                                              "anticipation": False}),
                Variant("scene graph, with anticipation", {"policy_config": {"scene_graph": True},
                                                           "anticipation": True}))),
        Preset("policies", "Policy backends side by side",
               "Paper (R2R-CE val-unseen, GPT-5.1): NE 4.42, OSR 76.0, SR 66.0, SPL 54.4, nDTW 69.5.",
               _policy_variants()),
        *_mllm_presets(),
    )}


@dataclass
class PresetReport:
    preset: Preset
    rows: list[dict[str, Any]]
    reports: list[RunReport]
    table_md: Path
    table_csv: Path
    plot_png: Path


def run_preset(name: str, episodes: Sequence[Episode], gt: dict[str, GroundTruth] | None, base: RunConfig,
               out_dir: Path | str, gateway: GatewayClient, scenes: SceneLoader | None, *,
               map_cache: SceneMapIndex | None = None, progress: bool = True,
               lanes: Sequence[Lane] = (), chunk: int | None = None) -> PresetReport:
    """Run every variant of preset ``name`` into ``out_dir/<name>/<variant>`` and write its table and plot
    (``lanes``: more robots, see :class:`EvalRunner`; ``chunk``: variants take turns, see the module)."""
    if chunk is not None and chunk < 1:
        raise ConfigError(f"chunk must be >= 1, got {chunk}")
    table = presets()
    if name not in table:
        raise ConfigError(f"unknown preset {name!r}; known: {', '.join(table)}")
    preset = table[name]
    root = Path(out_dir) / name
    cache = map_cache or SceneMapIndex(Path(out_dir) / "maps.json")
    configs = [RunConfig.model_validate({**base.model_dump(), **v.overrides}) for v in preset.variants]  # validated
    total = min(len(episodes), base.limit or len(episodes))
    limits = list(range(chunk, total, chunk)) + [total] if chunk else [total]
    reports: list[RunReport] = []
    for limit in limits:
        reports = []
        for v, cfg in zip(preset.variants, configs):
            log.info("preset %s: variant %s (%d episodes)", name, v.label, limit)
            runner = EvalRunner(gateway, scenes, cfg.model_copy(update={"limit": limit}), root / v.slug,
                                map_cache=cache, label=v.label, progress=progress, lanes=lanes)
            reports.append(runner.run(episodes, gt))
        # Tables after every round: a preset stopped midway still has its paired comparison so far.
        rows = [r.row for r in reports]
        md, csv = write_tables(rows, root / "table", COLUMNS, title=preset.title)
        with open(md, "a", encoding="utf-8") as f:
            f.write(f"\n{preset.paper}\n")
            f.write(comparison_markdown([(v.label, {r.episode_id: r for r in rep.results})
                                         for v, rep in zip(preset.variants, reports)]))
        png = plot_rows(rows, root / "plot.png", preset.title)
    return PresetReport(preset, rows, reports, md, csv, png)


def plot_rows(rows: Sequence[dict[str, Any]], path: Path | str, title: str) -> Path:
    """Grouped bars of SR/OSR/SPL/nDTW (percent) per variant and NE (metres) beside them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = [str(r["label"]) for r in rows]
    x = np.arange(len(rows))
    width = 0.8 / len(PLOT_METRICS)
    fig, (ax, ax_ne) = plt.subplots(1, 2, figsize=(4 + 2.2 * len(rows), 4.2),
                                    gridspec_kw={"width_ratios": [3, 1]})
    try:
        for k, m in enumerate(PLOT_METRICS):
            vals = [np.nan if r.get(m) is None else float(r[m]) for r in rows]
            bars = ax.bar(x + (k - (len(PLOT_METRICS) - 1) / 2) * width, vals, width, label=m)
            ax.bar_label(bars, fmt="%.0f", fontsize=7, padding=1)
        ax.set_xticks(x, labels)
        ax.set_ylim(0, 105)
        ax.set_ylabel("%")
        ax.legend(ncols=len(PLOT_METRICS), fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12))
        ax.set_title(title, fontsize=10)
        ne = [np.nan if r.get("NE") is None else float(r["NE"]) for r in rows]
        ax_ne.bar(x, ne, 0.6, color="tab:gray")
        ax_ne.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
        ax_ne.set_ylabel("NE (m)")
        ax_ne.set_title("navigation error", fontsize=10)
        counts = ", ".join(f"{r['label']}: n={r['count']}" for r in rows)
        fig.text(0.01, 0.01, counts, fontsize=7, color="dimgray")
        fig.tight_layout()
        fig.savefig(path, dpi=120)
    finally:
        plt.close(fig)
    return path
