"""A job's trajectory as CSV: one row per pose, world frame (metres, z up, heading from +x to +y)."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from typing import Any

COLUMNS = ["step", "x_m", "y_m", "z_m", "heading_rad", "timestamp_s", "action", "distance_m"]


def trajectory_csv(poses: Sequence[dict[str, Any]]) -> str:
    """``poses``: dicts with ``position_m`` (x, y, z) and optional ``step``, ``heading_rad``,
    ``timestamp_s``, ``action`` (the decision that led away from this pose). ``distance_m`` is the
    path length walked so far."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    walked = 0.0
    prev = None
    for i, p in enumerate(poses):
        x, y, z = (float(v) for v in p["position_m"])
        if prev is not None:
            walked += math.dist(prev, (x, y, z))
        prev = (x, y, z)
        h = p.get("heading_rad")
        t = p.get("timestamp_s")
        w.writerow([p.get("step", i), f"{x:.4f}", f"{y:.4f}", f"{z:.4f}",
                    "" if h is None else f"{float(h):.5f}", "" if t is None else f"{float(t):.3f}",
                    p.get("action", ""), f"{walked:.4f}"])
    return buf.getvalue()
