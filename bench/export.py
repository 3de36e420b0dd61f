"""Recording and export benchmark (issue 18): what writing a job's .rrd and a map's exports costs.

    python -m bench.export [--points 1000000] [--steps 25 40] [--repeats 3]

* ``.rrd`` of a mission: ``steps`` step events shaped like the planner's (7 candidates, panorama,
  spatial map and 14 candidate JPEGs of 128 px each) plus the map cloud (up to 500k points kept);
  wall time and file size;
* Nav2 map (occupancy + PGM + YAML), binary PCD and PLY of a ``points`` cloud (a generated room shell).
The first .rrd includes importing rerun (reported apart).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import Timer, table
from shared.cloud import PointCloud, encode
from shared.events import jpeg
from shared.export import encode_pcd, nav2_files, occupancy_from_cloud
from shared.recording import RecordedEvent, RecordingInput, write_recording
from shared.schemas import JobEventKind, JobState


def room_cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 20 m x 15 m floor with walls every 5 m: points on the floor (60 %) and on the walls."""
    rng = np.random.default_rng(seed)
    nf = int(0.6 * n)
    floor = np.column_stack([rng.uniform(0, 20, nf), rng.uniform(0, 15, nf), np.zeros(nf)])
    nw = n - nf
    t, z = rng.uniform(0, 1, nw), rng.uniform(0, 2.5, nw)
    k = rng.integers(0, 8, nw)
    x = np.where(k < 5, 5.0 * k, 20 * t)
    y = np.where(k < 5, 15 * t, 5.0 * (k - 5))
    walls = np.column_stack([x, y, z])
    xyz = np.concatenate([floor, walls]).astype(np.float32)
    return xyz, rng.integers(0, 256, (n, 3), dtype=np.uint8)


def mission_events(steps: int, seed: int = 0) -> list[RecordedEvent]:
    rng = np.random.default_rng(seed)
    img = lambda w, h: jpeg(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), 80)  # noqa: E731
    out = [RecordedEvent(0, JobEventKind.STARTED, JobState.RUNNING, 0, time.time(),
                    {"pose": {"position_m": [0, 0, 0], "heading_rad": 0.0}, "options": {"goal_m": [5, 5, 0]}})]
    pos = np.zeros(3)
    for s in range(steps):
        cands = [{"index": i, "kind": "waypoint", "dx_m": float(np.cos(i)), "dy_m": float(np.sin(i))} for i in range(6)]
        cands.append({"index": 6, "kind": "stop"})
        images = {"panorama": img(96 * 12, 96), "map": img(512, 512)}
        for i in range(7):
            images[f"cand_{i}_observed"] = img(128, 128)
            images[f"cand_{i}_anticipated"] = img(128, 128)
        out.append(RecordedEvent(s + 1, JobEventKind.STEP, JobState.RUNNING, s, time.time(), {
            "pose": {"position_m": pos.tolist(), "heading_rad": 0.3 * s}, "candidates": cands,
            "decision": {"candidate_index": s % 6, "kind": "waypoint", "reasoning": "the doorway ahead " * 10},
            "timings_s": {"observe_s": 0.1, "anticipation_s": 0.2, "decide_s": 0.01}}, images))
        pos = pos + np.array([0.5, 0.2, 0.0])
    out.append(RecordedEvent(steps + 1, JobEventKind.FINISHED, JobState.SUCCEEDED, steps, time.time(),
                        {"trajectory_m": [[0.5 * i, 0.2 * i, 0.0] for i in range(steps + 1)], "stop_called": True}))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--steps", type=int, nargs="+", default=[25, 40])
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    xyz, rgb = room_cloud(a.points)
    with Timer() as t_imp:
        import rerun  # noqa: F401
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for steps in a.steps:
            events = mission_events(steps)
            times, size = [], 0
            for r in range(a.repeats):
                path = Path(tmp) / f"m{steps}-{r}.rrd"
                with Timer() as t:
                    write_recording(RecordingInput(f"m{steps}", "mission", events, xyz, rgb, "bench"), path)
                times.append(t.s)
                size = path.stat().st_size
            rows.append((f".rrd, {steps} steps + {min(len(xyz), 500_000)} map points", float(np.median(times)),
                         f"{size / 1e6:.1f} MB"))
    for name, fn in [
        ("Nav2 (occupancy + PGM + YAML, 5 cm)", lambda: nav2_files(occupancy_from_cloud(xyz), "m")),
        ("PCD binary", lambda: encode_pcd(xyz, rgb)),
        ("PLY binary", lambda: encode(PointCloud(xyz, rgb))),
    ]:
        ts = []
        for _ in range(a.repeats):
            with Timer() as t:
                out = fn()
            ts.append(t.s)
        size = sum(len(v) for v in out.values()) if isinstance(out, dict) else len(out)
        rows.append((f"{name}, {len(xyz)} points", float(np.median(ts)), f"{size / 1e6:.1f} MB"))
    table(f"recordings and exports (median of {a.repeats}; import rerun {t_imp.s:.2f} s)", rows,
          ("what", "wall s", "size"))


if __name__ == "__main__":
    main()
