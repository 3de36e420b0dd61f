"""Per-episode pictures: a top-down plot of the reference path against the agent's path.

Each plot shows the start, the goal with the success radius, the reference path, the agent's path
(backtrack moves in their own colour), where the agent stopped (or where its step budget ran out),
and the instruction. ``write_episode_plots`` puts them in ``<run>/plots/`` and returns the rows that
:func:`evaluation.runner.EvalRunner` links from ``summary.md``; a run with plots off
(``RunConfig.plots``) lists the same episodes there without pictures.
"""

from __future__ import annotations

import logging
import re
import textwrap
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evaluation.results import EpisodeResult

log = logging.getLogger(__name__)

PLOTS_DIR = "plots"
SUCCESS_RADIUS_M = 3.0


@dataclass(frozen=True)
class EpisodeGeometry:
    """What the result does not hold: where the episode starts, its goal and its reference path (world)."""

    start_m: np.ndarray
    goal_m: np.ndarray
    reference_m: np.ndarray | None = None


def plot_name(episode_id: str) -> str:
    """A file name for any episode id (ids of real datasets are integers, generated ones may not be)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", str(episode_id))[:100] + ".png"


def backtrack_segments(result: EpisodeResult) -> list[int]:
    """Indices i whose move trajectory[i] -> trajectory[i+1] was a backtrack (decision i is the one
    taken at trajectory[i]: the planner appends one position per decision that moves)."""
    kinds = [str(d.get("kind", "")) for d in sorted(result.decisions, key=lambda d: d.get("step", 0))]
    n = len(result.trajectory_m)
    return [i for i, k in enumerate(kinds) if k == "backtrack" and i + 1 < n]


def plot_episode(result: EpisodeResult, geo: EpisodeGeometry, path: Path | str,
                 success_radius_m: float = SUCCESS_RADIUS_M) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    path = Path(path)
    traj = np.asarray(result.trajectory_m, float).reshape(-1, 3)
    fig, ax = plt.subplots(figsize=(6.4, 6.4), dpi=110)
    try:
        ref = geo.reference_m
        if ref is not None and len(ref) >= 2:
            ax.plot(ref[:, 0], ref[:, 1], "--", color="0.45", lw=2, marker="o", ms=3, label="reference path",
                    zorder=2)
        ax.add_patch(plt.Circle(geo.goal_m[:2], success_radius_m, color="tab:red", alpha=0.08, zorder=1))
        ax.add_patch(plt.Circle(geo.goal_m[:2], success_radius_m, fill=False, ls=":", color="tab:red", zorder=1))
        back = set(backtrack_segments(result))
        for i in range(len(traj) - 1):
            colour = "tab:purple" if i in back else "tab:blue"
            ax.annotate("", traj[i + 1, :2], traj[i, :2], zorder=3,
                        arrowprops=dict(arrowstyle="-|>", color=colour, lw=2.2 if i in back else 1.8,
                                        shrinkA=0, shrinkB=0, mutation_scale=12))
        if len(traj):
            ax.scatter(traj[:, 0], traj[:, 1], s=10, color="tab:blue", zorder=4)
        ax.scatter(*geo.start_m[:2], marker="^", s=150, color="tab:green", edgecolor="k", zorder=5)
        ax.scatter(*geo.goal_m[:2], marker="*", s=260, color="tab:red", edgecolor="k", zorder=5)
        m = result.metrics or {}
        stopped = bool(m.get("stop_called", result.state == "succeeded"))
        if len(traj):
            end = traj[-1, :2]
            if stopped:
                ax.scatter(*end, marker="X", s=170, color="k", zorder=6)
            else:
                ax.scatter(*end, marker="o", s=150, facecolor="none", edgecolor="k", lw=2, zorder=6)
        floors = np.ptp(np.concatenate([traj[:, 2], [geo.start_m[2], geo.goal_m[2]]])) > 1.5 if len(traj) else False
        handles = [
            Line2D([], [], ls="--", color="0.45", marker="o", ms=3, label="reference path"),
            Line2D([], [], color="tab:blue", lw=2, label="agent path"),
            Line2D([], [], color="tab:purple", lw=2.2, label=f"backtrack ({len(back)})"),
            Line2D([], [], ls="", marker="^", ms=10, color="tab:green", mec="k", label="start"),
            Line2D([], [], ls="", marker="*", ms=14, color="tab:red", mec="k", label="goal"),
            Line2D([], [], ls=":", color="tab:red", label=f"success radius {success_radius_m:g} m"),
            Line2D([], [], ls="", marker="X", ms=10, color="k", label="stop") if stopped else
            Line2D([], [], ls="", marker="o", ms=10, mfc="none", mec="k", label="step budget ran out"),
        ]
        ax.legend(handles=handles, loc="best", fontsize=7, framealpha=0.85)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")

        def num(k, fmt):
            v = m.get(k)
            return "-" if v is None else format(v, fmt)

        verdict = "success" if m.get("success") else "failure"
        title = (f"episode {result.episode_id}: {verdict}  NE {num('ne_m', '.2f')} m  nDTW {num('ndtw', '.2f')}  "
                 f"TL {num('tl_m', '.1f')} m  steps {num('steps', 'd')}" + ("  (several floors)" if floors else ""))
        ax.set_title(title, fontsize=9)
        if result.instruction:
            fig.text(0.5, 0.01, "\n".join(textwrap.wrap(result.instruction, 110)[:4]), ha="center", va="bottom",
                     fontsize=7, style="italic")
            fig.subplots_adjust(bottom=0.16)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path)
    finally:
        plt.close(fig)
    return path


def plotted_results(results: Iterable[EpisodeResult]) -> list[EpisodeResult]:
    """The results an episode plot is drawn for: ``done``, with a trajectory."""
    return [r for r in results if r.status == "done" and r.trajectory_m]


def write_episode_plots(results: Iterable[EpisodeResult], geometry: Mapping[str, EpisodeGeometry],
                        out_dir: Path | str) -> list[tuple[EpisodeResult, str]]:
    """A plot per ``done`` result that has its geometry; returns (result, path relative to out_dir)."""
    out_dir = Path(out_dir)
    rows = []
    for r in plotted_results(results):
        geo = geometry.get(str(r.episode_id))
        if geo is None:
            continue
        rel = f"{PLOTS_DIR}/{plot_name(r.episode_id)}"
        path = out_dir / rel
        if path.is_file() and path.stat().st_mtime >= r.finished_at_s:
            # Drawn after this result ended: a resumed run (or a preset's next round) redraws only new results.
            rows.append((r, rel))
            continue
        try:
            plot_episode(r, geo, path)
        except Exception:  # noqa: BLE001 - a bad picture must not lose the run's tables
            log.exception("could not plot episode %s", r.episode_id)
            continue
        rows.append((r, rel))
    return rows


def plots_markdown(rows: list[tuple[EpisodeResult, str | None]], drawn: bool = True) -> str:
    """The summary.md section listing the episodes and linking every plot (``rel`` None: no plot, and
    ``drawn`` False: the run's plots were off, which the section says)."""
    if not rows:
        return ""
    lines = ["", f"## Episodes ({len(rows)})", ""]
    if not drawn:
        # Plots from an earlier attempt of a resumed run may still lie in plots/: not linked, they may be stale.
        lines += ["Plots off (`--no-plots`): no episode plot was drawn.", ""]
    lines += ["| episode | success | NE (m) | nDTW | steps | backtracks | plot | recording |",
              "|---|---|---:|---:|---:|---:|---|---|"]
    for r, rel in rows:
        m = r.metrics or {}
        ne = "-" if m.get("ne_m") is None else f"{m['ne_m']:.2f}"
        nd = "-" if m.get("ndtw") is None else f"{m['ndtw']:.2f}"
        lines.append(f"| {r.episode_id} | {'yes' if m.get('success') else 'no'} | {ne} | {nd} | {m.get('steps', '-')} "
                     f"| {len(backtrack_segments(r))} | " + (f"[{Path(rel).name}]({rel}) | " if rel else "- | ")
                     + (f"[{Path(r.recording).name}]({r.recording}) |" if r.recording else "- |"))
    return "\n".join(lines) + "\n"
