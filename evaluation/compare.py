"""Paired comparison of evaluation runs: SR / SPL / nDTW differences with paired bootstrap intervals.

Variants of an ablation run the same episodes, so their difference is measured per episode and the
episodes are resampled together (a paired bootstrap: one draw of episode ids serves both runs). That
interval is much narrower than the one of two independent means when most episodes succeed or fail in
both. Only episodes ``done`` in both runs count (an error or a skip in either leaves the pair out).

    python -m evaluation.compare runs/ablations/anticipation/with_anticipation \\
        runs/ablations/anticipation/without_anticipation [--resamples 10000] [--out table]

A run may be several folders joined by commas, one per episode set (``A0,A1,A2 B0,B1,B2``): the
sets' pairs are pooled (set k of one run pairs with set k of the other; episode ids only need to be
unique within a set), so independent sets that each give a wide interval give one narrower one.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evaluation.errors import ConfigError
from evaluation.results import EpisodeResult, ResultsLog

RESULTS_FILE = "results.jsonl"  # the runner's log name (evaluation.runner.RESULTS_FILE)
# metric name -> (key of EpisodeResult.metrics, scale to the table's unit): percent like the tables.
METRICS: dict[str, tuple[str, float]] = {"SR": ("success", 100.0), "SPL": ("spl", 100.0), "nDTW": ("ndtw", 100.0)}


@dataclass(frozen=True)
class PairedDiff:
    """``b - a`` of one metric over the paired episodes, with its bootstrap interval."""

    metric: str
    n: int
    mean_a: float
    mean_b: float
    diff: float
    lo: float
    hi: float
    only_a: int | None = None  # SR: episodes that succeed only in a
    only_b: int | None = None


def paired_values(a: dict[str, EpisodeResult], b: dict[str, EpisodeResult], key: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-episode values of ``key`` where both runs are done and both have it, in a's order."""
    xs, ys = [], []
    for eid, ra in a.items():
        rb = b.get(eid)
        if rb is None or ra.status != "done" or rb.status != "done" or not ra.metrics or not rb.metrics:
            continue
        va, vb = ra.metrics.get(key), rb.metrics.get(key)
        if va is None or vb is None:
            continue
        xs.append(float(va))
        ys.append(float(vb))
    return np.asarray(xs), np.asarray(ys)


def paired_bootstrap(x: np.ndarray, y: np.ndarray, *, resamples: int = 10_000, level: float = 0.95,
                     seed: int = 0) -> tuple[float, float, float]:
    """(mean of y - x, lower, upper): percentile interval of the mean paired difference."""
    if x.shape != y.shape or x.ndim != 1:
        raise ConfigError(f"paired samples must be 1-D and of one length, got {x.shape} and {y.shape}")
    if not 0.0 < level < 1.0 or resamples < 1:
        raise ConfigError(f"need 0 < level < 1 and resamples >= 1, got {level}, {resamples}")
    d = y - x
    if len(d) == 0:
        return float("nan"), float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    means = np.empty(resamples)
    for start in range(0, resamples, 1000):  # chunks keep the index matrix small
        k = min(1000, resamples - start)
        means[start:start + k] = d[rng.integers(0, len(d), size=(k, len(d)))].mean(axis=1)
    alpha = (1.0 - level) / 2.0
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha])
    return float(d.mean()), float(lo), float(hi)


def compare_runs(a: dict[str, EpisodeResult], b: dict[str, EpisodeResult], *, resamples: int = 10_000,
                 level: float = 0.95, seed: int = 0) -> list[PairedDiff]:
    """SR, SPL and nDTW of ``b`` against ``a`` over their paired episodes."""
    out = []
    for name, (key, scale) in METRICS.items():
        x, y = paired_values(a, b, key)
        diff, lo, hi = paired_bootstrap(x * scale, y * scale, resamples=resamples, level=level, seed=seed)
        only = (int(((x > 0) & (y == 0)).sum()), int(((y > 0) & (x == 0)).sum())) if key == "success" else (None, None)
        out.append(PairedDiff(name, len(x), float(x.mean() * scale) if len(x) else float("nan"),
                              float(y.mean() * scale) if len(y) else float("nan"), diff, lo, hi, *only))
    return out


def comparison_markdown(runs: Sequence[tuple[str, dict[str, EpisodeResult]]], *, resamples: int = 10_000,
                        level: float = 0.95, seed: int = 0) -> str:
    """Every run against the first one, one table row per metric ("diff" is the run minus the first)."""
    if len(runs) < 2:
        return ""
    base_label, base = runs[0]
    lines = [f"\nPaired differences against **{base_label}** (same episodes, {resamples} bootstrap resamples, "
             f"{100 * level:.0f} % percentile intervals):\n",
             "| variant | metric | n | " + base_label.replace("|", "/") + " | variant value | diff | "
             f"{100 * level:.0f}% CI | only base / only variant |",
             "|---|---|---:|---:|---:|---:|---|---|"]
    for label, res in runs[1:]:
        for p in compare_runs(base, res, resamples=resamples, level=level, seed=seed):
            only = "" if p.only_a is None else f"{p.only_a} / {p.only_b}"
            lines.append(f"| {label} | {p.metric} | {p.n} | {p.mean_a:.1f} | {p.mean_b:.1f} | {p.diff:+.1f} | "
                         f"[{p.lo:+.1f}, {p.hi:+.1f}] | {only} |")
    return "\n".join(lines) + "\n"


def pool_sets(per_set: Sequence[dict[str, EpisodeResult]]) -> dict[str, EpisodeResult]:
    """One run's results over its episode sets: with several sets each episode id is prefixed by its
    set's position (``"1:17"``), since ids repeat from set to set; one set is returned as it is."""
    if len(per_set) == 1:
        return per_set[0]
    return {f"{k}:{eid}": r for k, res in enumerate(per_set) for eid, r in res.items()}


def pooled_run(folders: Sequence[Path]) -> tuple[str, dict[str, EpisodeResult]]:
    """(label, results) of one run over one or more episode sets (their folders), pooled by ``pool_sets``."""
    per_set = []
    for folder in folders:
        res = ResultsLog(folder / RESULTS_FILE).load()
        if not res:
            raise ConfigError(f"{folder}: no {RESULTS_FILE}")
        per_set.append(res)
    label = folders[0].name if len(folders) == 1 else f"{folders[0].name} ({len(folders)} sets)"
    return label, pool_sets(per_set)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="paired bootstrap comparison of run folders (the first is the base)")
    ap.add_argument("dirs", nargs="+", help="run folders; a run over several episode sets: folders joined by commas")
    ap.add_argument("--resamples", type=int, default=10_000)
    ap.add_argument("--level", type=float, default=0.95)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="also write the table to this .md file")
    a = ap.parse_args(argv)
    if len(a.dirs) < 2:
        ap.error("give at least two run folders")
    specs = [[Path(p) for p in str(d).split(",") if p] for d in a.dirs]
    if len({len(s) for s in specs}) != 1:
        ap.error("every run needs as many folders (episode sets) as the first: "
                 + " vs ".join(str(len(s)) for s in specs))
    runs = []
    for folders in specs:
        try:
            runs.append(pooled_run(folders))
        except ConfigError as exc:
            ap.error(str(exc))
    md = comparison_markdown(runs, resamples=a.resamples, level=a.level, seed=a.seed)
    print(md)
    if a.out:
        a.out.write_text(md, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
