"""Per-episode results (one JSON line each), resumable logs, and summary tables (Markdown + CSV).

The JSON-lines log is the run's source of truth: the summary is always recomputed from it, so an
interrupted run that is resumed, or a log merged by hand, gives the same table as one straight run.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from evaluation.errors import ResultsFormatError
from evaluation.ledger import LEDGER_COLUMNS, ledger_row
from shared.vln_metrics import EpisodeMetrics, MetricsError, summarize

log = logging.getLogger(__name__)

Status = Literal["done", "skipped", "error", "stopped"]


class EpisodeResult(BaseModel):
    """One episode of a run, as written to ``results.jsonl``.

    ``status``: ``done`` (the mission ended and has metrics, success or not), ``skipped`` (never run:
    its scene is missing, ``reason`` says why) or ``error`` (the system failed: timeout, a service
    error; retried when the run is resumed) or ``stopped`` (cancelled mid-way because the run's budget was
    reached: neither a failure of the policy nor of the system; always run again when the run is resumed).
    """

    model_config = ConfigDict(extra="allow")

    episode_id: str
    scene_id: str
    status: Status
    reason: str = ""
    instruction: str = ""
    mission_id: str | None = None
    map_id: str | None = None
    map_source: str | None = None
    state: str | None = None
    seed: int | None = None
    options: dict[str, Any] = Field(default_factory=dict)
    trajectory_m: list[list[float]] = Field(default_factory=list)
    decisions: list[dict[str, Any]] = Field(default_factory=list)
    metrics: dict[str, Any] | None = None
    step_latency_s: list[float] = Field(default_factory=list)
    prompt_tokens: int = 0
    completion_tokens: int = 0
    cost_usd: float = 0.0
    ledger: list[dict[str, Any]] = Field(default_factory=list)  # per step (evaluation.ledger.step_ledger)
    stage_s: dict[str, float] = Field(default_factory=dict)  # seconds per stage over the episode
    wall_s: float = 0.0
    finished_at_s: float = 0.0
    recording: str | None = None  # the mission's .rrd, relative to the run folder (runs with --record)

    def episode_metrics(self) -> EpisodeMetrics | None:
        return None if self.metrics is None else metrics_from_dict(self.metrics)


_METRIC_FIELDS = {f.name for f in fields(EpisodeMetrics)}
_NULLABLE = {"ne_m", "oracle_ne_m", "ndtw", "sdtw", "shortest_m"}


def metrics_from_dict(d: dict[str, Any]) -> EpisodeMetrics:
    """An :class:`EpisodeMetrics` from its ``to_dict()``; a nullable field that is absent reads as None
    (the gateway's mission record drops null values), anything else missing is an error."""
    missing = sorted(_METRIC_FIELDS - _NULLABLE - set(d))
    if missing:
        raise MetricsError(f"metrics lack {', '.join(missing)} (not VLN-CE episode metrics)")
    kw = {k: d.get(k) for k in _METRIC_FIELDS}
    for k in ("success", "oracle_success", "stop_called", "goal_reachable"):
        kw[k] = bool(kw[k])
    kw["steps"] = int(kw["steps"])
    return EpisodeMetrics(**kw)


class ResultsLog:
    """Append-only JSON-lines log of :class:`EpisodeResult`; the last line of an episode wins.

    A run killed mid-write leaves at most a partial last line: it is dropped (with a warning) and cut
    off before the next append, so resuming never builds on a corrupt line. A bad line anywhere else
    means the file was edited and is an error.
    """

    def __init__(self, path: Path | str):
        self.path = Path(path)

    def load(self) -> dict[str, EpisodeResult]:
        """Latest result per episode id, in first-seen order."""
        out: dict[str, EpisodeResult] = {}
        for r in self.attempts():
            out[r.episode_id] = r
        return out

    def attempts(self) -> list[EpisodeResult]:
        """Every line, in order: each attempt of each episode (what a run spent, retries included)."""
        out: list[EpisodeResult] = []
        if not self.path.is_file():
            return out
        with open(self.path, "rb") as f:
            data = f.read()
        lines = data.split(b"\n")
        complete, tail = lines[:-1], lines[-1]
        for i, raw in enumerate(complete, start=1):
            if not raw.strip():
                continue
            try:
                r = EpisodeResult.model_validate_json(raw)
            except ValueError as exc:
                if i == len(complete) and not tail:
                    log.warning("%s: dropping an unreadable last line (%s)", self.path, exc)
                    continue
                raise ResultsFormatError(f"{self.path}:{i}: not an episode result ({exc})") from None
            out.append(r)
        if tail.strip():
            log.warning("%s: dropping a partial last line (%d bytes; the run was interrupted)", self.path, len(tail))
        return out

    def _cut_partial_tail(self) -> None:
        if not self.path.is_file():
            return
        with open(self.path, "rb+") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            if size == 0:
                return
            f.seek(-1, os.SEEK_END)
            if f.read(1) == b"\n":
                return
            data = (f.seek(0), f.read())[1]
            keep = data.rfind(b"\n") + 1
            f.truncate(keep)

    def append(self, result: EpisodeResult) -> None:
        """Write one result durably (flushed and fsynced: the resume point survives a crash)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._cut_partial_tail()
        line = result.model_dump_json() + "\n"
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())


# --- summary tables ----------------------------------------------------------------------------------

COLUMNS = ["label", "count", "skipped", "errors", "stopped", "NE", "OSR", "SR", "SPL", "nDTW", "SDTW", "TL", "steps",
           "unreachable", "step_s", "tokens", "cost_usd", *LEDGER_COLUMNS]
"""Summary columns: ``stopped`` counts the episodes the budget cancelled mid-way; NE/TL in metres, rates in
percent, ``step_s`` the mean step latency, ``tokens`` the mean LLM tokens per episode, ``cost_usd`` the
total; then the cost ledger's (:data:`LEDGER_COLUMNS`)."""


def summary_row(results: Iterable[EpisodeResult], label: str = "all") -> dict[str, Any]:
    """One table row: VLN-CE means over the ``done`` episodes (via :func:`shared.vln_metrics.summarize`),
    with counts of skipped, errored and budget-stopped episodes, latency and LLM usage."""
    res = list(results)
    done = [r for r in res if r.status == "done" and r.metrics is not None]
    row: dict[str, Any] = {c: None for c in COLUMNS}
    row.update(label=label, count=len(done), skipped=sum(r.status == "skipped" for r in res),
               errors=sum(r.status == "error" for r in res), stopped=sum(r.status == "stopped" for r in res))
    if done:
        try:
            s = summarize(r.episode_metrics() for r in done)
        except MetricsError as exc:
            raise ResultsFormatError(f"cannot summarise: {exc}") from None
        pct = s.as_percent_row()
        row.update({k: pct[k] for k in ("NE", "OSR", "SR", "SPL", "nDTW", "SDTW", "TL")})
        row["steps"] = round(s.steps, 2)
        row["unreachable"] = s.unreachable
        lat = [x for r in done for x in r.step_latency_s]
        row["step_s"] = round(float(np.mean(lat)), 3) if lat else None
        row["tokens"] = round(float(np.mean([r.prompt_tokens + r.completion_tokens for r in done])), 1)
        row["cost_usd"] = round(float(sum(r.cost_usd for r in done)), 4)
        row.update(ledger_row(done))
    return row


_DIGITS = {"NE": 2, "TL": 2, "steps": 1, "step_s": 3, "tokens": 0, "cost_usd": 4, "cost_usd_ep": 5,
           **{c: 4 for c in LEDGER_COLUMNS if c.endswith("_s")}}


def _cell(v: Any, column: str = "") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.{_DIGITS.get(column, 1)}f}"
    return str(v)


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str] = COLUMNS) -> str:
    """A GitHub-flavoured Markdown table; missing values print as ``-``."""
    head = "| " + " | ".join(columns) + " |"
    sep = "|" + "|".join("---" if c == "label" else "---:" for c in columns) + "|"
    body = ["| " + " | ".join(_cell(r.get(c), c) for c in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body]) + "\n"


def csv_table(rows: Sequence[dict[str, Any]], columns: Sequence[str] = COLUMNS) -> str:
    """CSV with a header; missing values are empty cells."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: "" if r.get(c) is None else r.get(c) for c in columns})
    return buf.getvalue()


def write_tables(rows: Sequence[dict[str, Any]], stem: Path | str, columns: Sequence[str] = COLUMNS,
                 title: str | None = None) -> tuple[Path, Path]:
    """Write ``<stem>.md`` and ``<stem>.csv``; returns both paths."""
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    md, cs = stem.with_suffix(".md"), stem.with_suffix(".csv")
    text = markdown_table(rows, columns)
    md.write_text((f"# {title}\n\n" if title else "") + text, encoding="utf-8")
    cs.write_text(csv_table(rows, columns), encoding="utf-8")
    return md, cs


def skipped_report(results: Iterable[EpisodeResult]) -> list[tuple[str, str, str]]:
    """(episode id, scene, reason) of every skipped or errored episode."""
    return [(r.episode_id, r.scene_id, f"{r.status}: {r.reason}") for r in results if r.status != "done"]
