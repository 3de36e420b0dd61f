"""``python -m bench.fleet``: evaluation throughput with N robots at once, against the LLM stand-in.

One system is started for the largest N (:class:`deploy.launcher.Launcher` with ``robots=N``: a robot-io
and a light gateway per robot, robot0..robotN-1; one planner, mapper, renderer and reconstructor shared
by all), and for each N ``evaluation run`` drives the first N gateways over a generated set of
``--houses`` houses x ``--per-house`` episodes, with the planner's openai policy talking to the stand-in
(:mod:`services.planner.tools.llm_standin`) at ``--latency-s`` per call. A warm-up pass first runs every
episode for one step on all robots (unmeasured): it uploads the curated maps and makes the shared renderer
index each of them once, as a real run does once per scene and then amortises over all its episodes (20
per house in ``make eval``); without it the few episodes per house here would be dominated by those
one-off costs, paid by whichever N ran first. The N are then run largest first.

Per N: episodes per minute over the episode phase (first mission start to last mission end, from
results.jsonl), the median seconds per step of each ledger stage, the planner-side median observe
(the panorama over the bus), and the load average. The simulator's own panorama median (robot-io's
``observe`` handler, from its telemetry) is read right after the largest N, whose run is the only one
those robot-ios have served so far. The last line is ``fleet speedup N=<max>: <x>x`` (episodes per
minute at the largest N over the smallest).

``--replica renderer=2`` runs two renderers (the planner's render requests go round-robin over the live
instances, each answered by one): the column "renders per replica" is each instance's share of that N's
render requests. Give each variant its own ``--out`` to keep both results.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import time
from pathlib import Path

from bench.common import table

STAGES = ("observe", "candidates", "anticipation", "map", "policy", "move")


def _rows(results: Path) -> list[dict]:
    return [json.loads(x) for x in results.read_text().splitlines() if x.strip()]


def _episode_phase_s(rows: list[dict]) -> tuple[int, float]:
    done = [r for r in rows if r["status"] == "done"]
    if not done:
        return 0, float("nan")
    starts = [r["finished_at_s"] - r["wall_s"] for r in done]
    return len(done), max(r["finished_at_s"] for r in done) - min(starts)


def _stage_medians(rows: list[dict]) -> dict[str, float]:
    """Median seconds per step of each stage, over every step of every finished episode."""
    per: dict[str, list[float]] = {s: [] for s in STAGES}
    for r in rows:
        for step in r.get("ledger") or []:
            for s in STAGES:
                per[s].append(float(step["stage_s"].get(s, 0.0)))
    return {s: statistics.median(v) if v else float("nan") for s, v in per.items()}


RENDER_ENDPOINTS = ("views", "spatial_map")  # the renderer's request endpoints (shared.keys.RENDER_*)


def _metrics(launcher) -> list:
    from shared.bus.typed import TypedBus
    from shared.clients import ServicesClient

    good, _ = ServicesClient(TypedBus(launcher.bus), timeout_s=3.0).metrics()
    return good


def _renders(launcher) -> dict[str, int]:
    """Render requests (views and spatial maps) each renderer instance has answered so far."""
    return {m.instance: sum(m.endpoints[e].requests for e in RENDER_ENDPOINTS if e in m.endpoints)
            for m in _metrics(launcher) if m.service == "renderer"}


def _panorama_ms(launcher, robots: int) -> tuple[float, int]:
    """Median of robot-io's ``observe`` handler over robot0..robot<robots-1> (request-weighted medians)."""
    good = _metrics(launcher)
    meds, count = [], 0
    for m in good:
        ep = m.endpoints.get("observe")
        if m.service == "robot_io" and ep is not None and ep.requests:
            meds += [ep.latency_p50_ms] * ep.requests
            count += ep.requests
    return (statistics.median(meds) if meds else float("nan")), count


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="1,2,4,8", help="comma-separated N values")
    ap.add_argument("--houses", type=int, help="scenes (default: the largest N, so every robot has one)")
    ap.add_argument("--per-house", type=int, default=2)
    ap.add_argument("--latency-s", type=float, default=2.0)
    ap.add_argument("--stop-after", type=int, default=4, help="LLM calls per episode (the stand-in stops then)")
    ap.add_argument("--replica", action="append", default=[], metavar="SERVICE=N",
                    help="replicas of a shared service (planner, mapper, renderer)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench/fleet"))
    ap.add_argument("--start-timeout-s", type=float, default=600.0, help="deadline for the system to come up")
    a = ap.parse_args(argv)
    from deploy.launcher import Launcher
    from evaluation.cli import _replicas
    from evaluation.cli import main as evaluation
    from evaluation.dataset import SetSpec, generate_set, write_set
    from services.planner.tools.llm_standin import StandinConfig, StandinServer

    ns = sorted({int(x) for x in a.robots.split(",") if x.strip()}, reverse=True)
    houses = a.houses or max(ns)
    episodes = a.out / f"set-{houses}x{a.per_house}.json.gz"
    if not episodes.is_file():
        ds, gt = generate_set(SetSpec(houses=houses, per_house=a.per_house, floors=(1,), seed=0), with_gt=True)
        write_set(ds, gt, episodes)
    shutil.rmtree(a.out / "system", ignore_errors=True)
    maps = a.out / "maps.json"
    maps.unlink(missing_ok=True)
    rows, rate, pano = [], {}, {}
    t_up = time.monotonic()
    def run(launcher, n: int, out: Path, max_steps: int) -> tuple[int, float, int]:
        shutil.rmtree(out, ignore_errors=True)
        cfg = StandinConfig(latency_s=a.latency_s, policy="straight", stop_after=a.stop_after)
        with StandinServer(cfg) as llm:
            policy = {"model": "gpt-4o-mini", "base_url": llm.url, "api_key": "bench"}
            gateways = [x for url in launcher.gateway_urls[:n] for x in ("--gateway", url)]
            t0 = time.monotonic()
            rc = evaluation(["run", "--episodes", str(episodes), "--policy", "openai", "--policy-config",
                             json.dumps(policy), "--map-source", "curated", "--max-steps", str(max_steps),
                             *gateways, "--maps", str(maps), "--out", str(out), "--no-progress"])
            return rc, time.monotonic() - t0, llm.stats.by_outcome.get("ok", 0)

    launcher = Launcher(a.out / "system", robots=max(ns), replicas=_replicas(a.replica))
    try:
        launcher.start(a.start_timeout_s)
        up_s = time.monotonic() - t_up
        rc, warm_s, _ = run(launcher, max(ns), a.out / "warm-up", 1)
        if rc != 0:
            raise SystemExit(f"the warm-up exited {rc}; see {a.out / 'warm-up'}")
        for n in ns:
            out = a.out / f"robots{n}"
            before = _renders(launcher)
            rc, wall, calls = run(launcher, n, out, a.stop_after + 2)
            # Each replica's share of this N's render requests: a request is answered by one instance.
            split = "/".join(str(v - before.get(k, 0)) for k, v in sorted(_renders(launcher).items()))
            load = os.getloadavg()[0]
            if rc != 0:
                raise SystemExit(f"evaluation with {n} robots exited {rc}; see {out}")
            if n == max(ns):
                pano[n] = _panorama_ms(launcher, n)
            res = _rows(out / "results.jsonl")
            count, phase = _episode_phase_s(res)
            rate[n] = 60.0 * count / phase
            st = _stage_medians(res)
            cpu_step = st["observe"] + st["candidates"] + st["anticipation"] + st["map"]
            rows.append((n, count, calls, round(phase, 1), round(rate[n], 2), round(wall, 1),
                         round(1000 * st["observe"]), round(1000 * st["candidates"]), round(1000 * st["anticipation"]),
                         round(1000 * st["map"]), round(1000 * st["move"]), round(cpu_step, 3), split, f"{load:.1f}"))
    finally:
        launcher.stop()
    rows.sort()
    low = min(ns)
    rows = [(*r[:5], round(rate[r[0]] / rate[low], 2), *r[5:]) for r in rows]
    renderers = _replicas(a.replica).get("renderer", 1)
    table(f"Fleet: stand-in at {a.latency_s:g} s per call, {a.stop_after} calls per episode, {renderers} renderer(s), "
          f"system up in "
          f"{up_s:.0f} s, warm-up {warm_s:.0f} s (median ms per step per stage, from the ledger)", rows,
          ("robots", "episodes", "LLM calls", "episode phase s", "episodes/min", "speedup", "wall s",
           "observe ms", "candidates ms", "anticipation ms", "map ms", "move ms", "pre-LLM s/step",
           "renders per replica", "load avg 1m"))
    top = max(ns)
    med, count = pano[top]
    print(f"\nsimulator panorama (robot-io observe handler, warm-up and N={top} runs) while {top} robots ran: "
          f"median {med:.1f} ms over {count} panoramas (target <= 60 ms)")
    # make eval's set is 5 houses x 20 episodes: whole scenes per robot, so at most 5 robots work at once.
    lanes = min(top, 5)
    robot_ep_s = top * 60.0 / rate[top]
    print(f"100 generated episodes (5 houses x 20, so {lanes} robots busy): about {20 * robot_ep_s / 60:.1f} min, "
          f"EXTRAPOLATED from {robot_ep_s:.1f} s per episode per robot at N={top} ({a.stop_after} calls of "
          f"{a.latency_s:g} s each; target <= 15 min)")
    print(f"fleet speedup N={top}: {rate[top] / rate[low]:.2f}x")


if __name__ == "__main__":
    main()
