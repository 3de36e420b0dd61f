"""The VLN-CE prediction file of a run: what ``run.py --run-type inference`` of VLN-CE writes.

VLN-CE's inference (``INFERENCE.PREDICTIONS_FILE``) stores, per episode id, the agent's states from the
start to the end: ``{"<episode_id>": [{"position": [x, y, z], "heading": h, "stop": bool}, ...]}``, with
positions in Habitat's y-up frame and ``heading`` the agent's rotation about +y (0 faces -z, positive
turns left), i.e. ``world heading - pi/2``; ``stop`` is true once the agent has called stop. Our
trajectories are world z-up; the one conversion is :func:`shared.geometry.world_to_habitat`.

Only episodes that ran (``done``, success or not) have a trajectory; skipped and errored ones are
left out and counted, so the leaderboard tooling does not mistake a system failure for a policy's path.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.results import EpisodeResult
from shared.geometry import world_to_habitat, wrap_angle

PREDICTIONS_FILE = "predictions.json"


def habitat_heading(world_heading_rad: float) -> float:
    """VLN-CE's heading (rotation about Habitat +y, 0 = facing -z) of a world heading (from +x to +y)."""
    return float(wrap_angle(world_heading_rad - math.pi / 2.0))


def episode_states(trajectory_m: np.ndarray, start_heading_rad: float | None, stop_called: bool) -> list[dict[str, Any]]:
    """The VLN-CE states of one trajectory (world, (T, 3)): the heading at a point is the direction the
    agent moved to reach it (it turns towards each waypoint), the start's is the episode's."""
    traj = np.asarray(trajectory_m, np.float64).reshape(-1, 3)
    hab = world_to_habitat(traj)
    heading = 0.0 if start_heading_rad is None else float(start_heading_rad)
    out = []
    for i in range(len(traj)):
        if i > 0:
            d = traj[i, :2] - traj[i - 1, :2]
            if np.hypot(*d) > 1e-6:  # a move that went nowhere keeps the heading
                heading = math.atan2(d[1], d[0])
        out.append({"position": [round(float(v), 6) for v in hab[i]], "heading": round(habitat_heading(heading), 6),
                    "stop": bool(stop_called and i == len(traj) - 1)})
    return out


def predictions(results: Iterable[EpisodeResult], start_headings: Mapping[str, float] | None = None
                ) -> tuple[dict[str, list[dict[str, Any]]], int]:
    """``(predictions, left_out)``: the file's content for the ``done`` results with a trajectory."""
    out: dict[str, list[dict[str, Any]]] = {}
    left_out = 0
    for r in results:
        if r.status != "done" or not r.trajectory_m:
            left_out += 1
            continue
        stop = bool((r.metrics or {}).get("stop_called", r.state == "succeeded"))
        out[str(r.episode_id)] = episode_states(np.asarray(r.trajectory_m), (start_headings or {}).get(str(r.episode_id)),
                                                stop)
    return out, left_out


def write_predictions(results: Iterable[EpisodeResult], path: Path | str,
                      start_headings: Mapping[str, float] | None = None) -> tuple[Path, int, int]:
    """Write the prediction file; returns (path, episodes written, episodes left out)."""
    preds, left_out = predictions(results, start_headings)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(preds, indent=1), encoding="utf-8")
    return path, len(preds), left_out
