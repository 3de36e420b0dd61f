"""bench/planner: the navigation loop on generated episodes, in-process (issue 7's figures).

* non-LLM step latency (observe -> candidates -> anticipated views -> map -> prompt ready), p50/p95;
* SR of the ``oracle`` policy (proves waypoints, motion, loop and metrics are sound; target >= 95 %);
* SR / SPL / nDTW of the offline ``heuristic`` default.

Maps are clouds sampled from the scene mesh (the "human-curated" cloud), 1e6 points at most.
"""

from __future__ import annotations

import argparse
import time

from bench.common import percentiles_ms, table
from evaluation.clouds import sample_scene_cloud
from services.mapper.core import PREDICTORS
from services.planner.core.local import LocalStack, episode_options
from services.renderer.core import MapRenderer, SpatialMapper
from libs.world import generate_episodes
from services.robot_io.core import ROBOTS
from libs.pointrender import RENDERERS, IndexedCloud
from shared.vln_metrics import summarize


def stack_for(scene: str) -> tuple[LocalStack, object]:
    robot = ROBOTS.create("sim", {"scene": scene})
    cloud = sample_scene_cloud(robot.scene, density_per_m2=300.0, max_points=1_000_000)
    renderer = RENDERERS.create("numpy")
    renderer.warm_up()
    port = MapRenderer(IndexedCloud(cloud), renderer, SpatialMapper())
    return LocalStack(robot, PREDICTORS.create("geometric"), port, cloud.label_names), robot


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", default=["generated:0", "generated:1", "generated:2:floors=2"])
    ap.add_argument("--episodes", type=int, default=4, help="per scene")
    ap.add_argument("--policies", nargs="+", default=["oracle", "heuristic"])
    ap.add_argument("--seed", type=int, default=11, help="episode generator seed")
    args = ap.parse_args(argv)
    results: dict[str, list] = {p: [] for p in args.policies}
    latencies: list[float] = []
    t0 = time.time()
    for scene in args.scenes:
        stack, robot = stack_for(scene)
        eps = generate_episodes(robot.scene, robot.nav, args.episodes, seed=args.seed).episodes
        for ep in eps:
            for policy in args.policies:
                out = stack.run(ep.instruction, episode_options(ep, policy, max_steps=30))
                results[policy].append(out.episode_metrics)
                latencies += out.step_latency_s
        robot.close()
    rows = []
    for policy, ms in results.items():
        s = summarize(ms)
        rows.append((policy, s.episodes, 100 * s.sr, 100 * s.osr, 100 * s.spl, 100 * s.ndtw, s.ne_m, s.tl_m))
    table(f"planner: generated episodes ({len(args.scenes)} houses x {args.episodes}, seed {args.seed}), "
          "sampled-mesh maps",
          rows, ("policy", "episodes", "SR %", "OSR %", "SPL %", "nDTW %", "NE m", "TL m"))
    p = percentiles_ms(latencies, (50, 95))
    table("planner: non-LLM step latency (observe -> prompt ready), 256x256, 1e6-point maps",
          [("step", len(latencies), p["p50"], p["p95"], "target p50 <= 150 ms")],
          ("what", "steps", "p50 ms", "p95 ms", "target"))
    print(f"\n(wall time {time.time() - t0:.0f} s)")
    return {"latency_p50_ms": p["p50"]}


if __name__ == "__main__":
    main()
