"""``make demo``: the whole method on the embedded default, through the system as a user drives it.

1. start a zenoh router and the six services as separate processes (deploy.launcher) and wait until
   every one is alive;
2. pre-explore the generated house and reconstruct it (``POST /explorations``): the mapper drives
   robot-io, the reconstructor builds and stores the map;
3. follow a generated instruction with the offline heuristic policy (``POST /missions``), printing
   every step from the live event stream, then the VLN-CE metrics;
4. stop every process cleanly (also on Ctrl-C).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import httpx

from deploy.launcher import Launcher
from shared.logs import configure_logging


def say(msg: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def make_episode(scene: str, seed: int):
    """A generated R2R-style episode in the scene robot-io simulates (same generator, same seed)."""
    from services.robot_io.core import ROBOTS, generate_episodes

    with ROBOTS.create("sim", {"scene": scene}) as robot:
        return generate_episodes(robot.scene, robot.nav, 1, seed=seed).episodes[0]


def wait_job(http: httpx.Client, url: str, deadline_s: float, show) -> dict:
    end = time.monotonic() + deadline_s
    last = None
    while time.monotonic() < end:
        rec = http.get(url).json()
        line = show(rec)
        if line and line != last:
            say(line)
            last = line
        if rec["state"] in ("succeeded", "failed", "cancelled"):
            return rec
        time.sleep(0.5)
    raise TimeoutError(f"{url} did not finish within {deadline_s:.0f} s")


def follow_mission(http: httpx.Client, mission_id: str, deadline_s: float) -> dict:
    """Print each step from the SSE stream (as the dashboard sees it) until the mission ends."""
    with http.stream("GET", f"/missions/{mission_id}/events", timeout=deadline_s) as stream:
        event, data = None, None
        for line in stream.iter_lines():
            if line.startswith("event:"):
                event = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                data = json.loads(line.split(":", 1)[1])
            elif not line and data is not None:
                if event == "step" or data.get("kind") == "step":
                    d = data.get("data", {})
                    dec = d.get("decision", {})
                    pos = d.get("pose", {}).get("position_m", [0, 0, 0])
                    t = d.get("timings_s", {})
                    say(f"  step {data.get('step'):>2}: at ({pos[0]:5.2f}, {pos[1]:5.2f})  "
                        f"{len(d.get('candidates', []))} candidates -> {dec.get('kind', '?')} #{dec.get('candidate_index')}"
                        f"  [{1000 * t.get('prompt_ready_s', 0):.0f} ms to prompt]  {str(dec.get('reasoning', ''))[:90]}")
                if event == "end" or data.get("kind") in ("finished", "error"):
                    break
                event, data = None, None
    return http.get(f"/missions/{mission_id}").json()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run-dir", default="runs/demo", help="logs, maps and the gateway database go here")
    ap.add_argument("--scene", default="generated:0", help="generated:<seed>[:floors=2] or a mesh file")
    ap.add_argument("--seed", type=int, default=3, help="episode seed")
    ap.add_argument("--renderers", type=int, default=1, help="renderer replicas")
    ap.add_argument("--policy", default="heuristic")
    args = ap.parse_args(argv)
    configure_logging("demo", "local", "WARNING")
    run_dir = Path(args.run_dir).resolve()
    t_start = time.time()
    env = {
        "ANT_ROBOT_CONFIG": json.dumps({"scene": args.scene}),
        "ANT_STORE_DIR": str(run_dir / "maps"),
        "ANT_DB_PATH": str(run_dir / "gateway.sqlite3"),
    }
    say(f"starting a zenoh router + 6 services (logs: {run_dir / 'logs'})")
    launcher = Launcher(run_dir, replicas={"renderer": args.renderers}, extra_env=env)
    ok = False
    try:
        launcher.start(deadline_s=120)
        say(f"all services alive after {time.time() - t_start:.1f} s: {launcher.alive()}")
        with httpx.Client(base_url=launcher.gateway_url, timeout=30) as http:
            for s in http.get("/status").json()["services"]:
                say(f"  {s['service']:<14} instances={s['instances']} backends={s['details'][0]['backends']}")
            say(f"dashboard: {launcher.gateway_url}/dashboard")

            say(f"1/2 pre-exploring and reconstructing {args.scene} ...")
            t0 = time.time()
            job = http.post("/explorations", json={"map_id": "demo-house"}).json()
            rec = wait_job(http, job["url"], 600,
                           lambda r: f"  exploration {r['state']:<9} {r.get('stage') or '':<15} {r.get('message') or ''}")
            if rec["state"] != "succeeded":
                raise RuntimeError(f"exploration {rec['state']}: {rec.get('error')}")
            info = http.get("/maps/demo-house").json()
            say(f"  map demo-house v{info['version']}: {info['point_count']:,} points, {info['regions']} regions, "
                f"scale factors {[round(x, 3) for x in info['scale_factors']]} ({time.time() - t0:.0f} s)")

            ep = make_episode(args.scene, args.seed)
            say(f"2/2 navigating: \"{ep.instruction}\"")
            options = {
                "policy": args.policy, "max_steps": 30, "start_pose": ep.start_pose.model_dump(),
                "goal_m": list(map(float, ep.goal_m)),
                "reference_path_m": [list(map(float, p)) for p in ep.reference_path_m],
            }
            mission = http.post("/missions", json={"instruction": ep.instruction, "map_id": "demo-house",
                                                   "options": options}).json()
            rec = follow_mission(http, mission["id"], 600)
            m = rec.get("metrics") or {}
            say(f"RESULT: mission {rec['state']} after {rec['step']} steps; "
                + ", ".join(f"{k}={m[k]:.2f}" if isinstance(m.get(k), float) else f"{k}={m.get(k)}"
                            for k in ("ne_m", "success", "oracle_success", "spl", "ndtw", "tl_m") if k in m))
            say(f"total {time.time() - t_start:.0f} s; the mission and its events stay in {env['ANT_DB_PATH']}")
            ok = rec["state"] in ("succeeded", "failed")
    except KeyboardInterrupt:
        say("interrupted")
    except Exception as exc:
        say(f"FAILED: {type(exc).__name__}: {exc} (logs in {run_dir / 'logs'})")
    finally:
        codes = launcher.stop()
        say(f"stopped every process: {codes}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
