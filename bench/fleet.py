"""``python -m bench.fleet``: evaluation throughput with N robots at once, against the LLM stand-in.

For each N it runs ``evaluation run --robots N`` (N whole systems, robot0..robotN-1, scenes sharded over
them) on a generated set of ``--houses`` houses x ``--per-house`` episodes, with the planner's openai
policy talking to the stand-in (:mod:`services.planner.tools.llm_standin`) at ``--latency-s`` per call.
Episodes per minute are counted over the episode phase (first mission start to last mission end, from
results.jsonl); system start-up and map uploads are reported apart. The last line is
``fleet speedup N=<max>: <x>x`` (episodes per minute at the largest N over N=1).

Every system is a full stack (six processes): on a 2-core machine N=8 is far past what fits; the
default runs N=1,2 and the issue's N=1,2,4,8 is ``--robots 1,2,4,8``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from bench.common import table


def _episode_phase_s(results: Path) -> tuple[int, float]:
    rows = [json.loads(x) for x in results.read_text().splitlines() if x.strip()]
    done = [r for r in rows if r["status"] == "done"]
    if not done:
        return 0, float("nan")
    starts = [r["finished_at_s"] - r["wall_s"] for r in done]
    return len(done), max(r["finished_at_s"] for r in done) - min(starts)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="1,2", help="comma-separated N values")
    ap.add_argument("--houses", type=int, help="scenes (default: the largest N, so every robot has one)")
    ap.add_argument("--per-house", type=int, default=2)
    ap.add_argument("--latency-s", type=float, default=2.0)
    ap.add_argument("--stop-after", type=int, default=4, help="LLM calls per episode (the stand-in stops then)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench/fleet"))
    a = ap.parse_args(argv)
    from evaluation.cli import main as evaluation
    from evaluation.dataset import SetSpec, generate_set, write_set
    from services.planner.tools.llm_standin import StandinConfig, StandinServer

    ns = sorted({int(x) for x in a.robots.split(",") if x.strip()})
    houses = a.houses or max(ns)
    episodes = a.out / f"set-{houses}x{a.per_house}.json.gz"
    if not episodes.is_file():
        ds, gt = generate_set(SetSpec(houses=houses, per_house=a.per_house, floors=(1,), seed=0), with_gt=True)
        write_set(ds, gt, episodes)
    rows, rate = [], {}
    for n in ns:
        out = a.out / f"robots{n}"
        shutil.rmtree(out, ignore_errors=True)
        cfg = StandinConfig(latency_s=a.latency_s, policy="straight", stop_after=a.stop_after)
        with StandinServer(cfg) as llm:
            policy = {"model": "gpt-4o-mini", "base_url": llm.url, "api_key": "bench"}
            t0 = time.monotonic()
            rc = evaluation(["run", "--episodes", str(episodes), "--policy", "openai", "--policy-config",
                             json.dumps(policy), "--map-source", "curated", "--max-steps", str(a.stop_after + 2),
                             "--robots", str(n), "--out", str(out), "--no-progress", "--start-timeout-s", "600"])
            wall = time.monotonic() - t0
            calls = llm.stats.by_outcome.get("ok", 0)
        if rc != 0:
            raise SystemExit(f"evaluation with {n} robots exited {rc}; see {out}")
        count, phase = _episode_phase_s(out / "results.jsonl")
        rate[n] = 60.0 * count / phase
        rows.append((n, count, calls, round(phase, 1), round(rate[n], 2), round(wall, 1)))
    table(f"Fleet: stand-in at {a.latency_s:g} s per call, {a.stop_after} calls per episode",
          rows, ("robots", "episodes", "LLM calls", "episode phase s", "episodes/min", "wall s (with start-up)"))
    top = max(ns)
    print(f"fleet speedup N={top}: {rate[top] / rate[ns[0]]:.2f}x")


if __name__ == "__main__":
    main()
