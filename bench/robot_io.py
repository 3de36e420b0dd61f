"""Benchmark of the robot-io simulator: panorama rendering and move_to steps.

    python -m bench.robot_io [--repeats 20]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import numpy as np

from services.robot_io.core.robot import SimConfig, SimRobot

REPLICA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "replica_office0" / "office0_mesh.ply"


def _median_ms(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm-up: the first cast builds Embree's BVH
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t) * 1e3)
    return statistics.median(ts), min(ts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    rows = []
    scenes = [("house 200 m2 (generated:0)", "generated:0")]
    if REPLICA.is_file():
        scenes.append(("Replica office0", str(REPLICA)))
    for name, spec in scenes:
        t = time.perf_counter()
        robot = SimRobot(SimConfig(scene=spec))
        load_s = time.perf_counter() - t
        med, best = _median_ms(robot.observe, args.repeats)
        rows.append((f"{name}: load + nav grid", load_s * 1e3, load_s * 1e3))
        rows.append((f"{name}: observe 12x256x256 RGB-D-sem", med, best))
        rng = np.random.default_rng(0)

        def one_step():
            # One 0.25 m move_to step in a random direction (blocked moves cost the same checks).
            a = rng.uniform(-math.pi, math.pi)
            robot.move_to(0.25 * math.cos(a), 0.25 * math.sin(a))

        med, best = _median_ms(one_step, args.repeats * 5)
        rows.append((f"{name}: move_to one 0.25 m step", med, best))
    print(f"{'benchmark':55s} {'median ms':>10s} {'min ms':>8s}")
    for n, m, b in rows:
        print(f"{n:55s} {m:10.2f} {b:8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
