"""Screenshots of the dashboard's candidate cards at every distance, from the real system (issue 20).

    python -m tools.candidate_cards --map runs/anticipation/maps/generated_0_rgbd_128.ply

1. starts the router and the six services (deploy.launcher), robot-io simulating ``--scene``;
2. imports the map (``POST /maps``: an agent-built cloud, e.g. one bench.anticipation built and cached);
3. picks start poses in the scene whose true depth straight ahead is < 1 m, 1-2 m and > 2 m (the bands of
   bench.anticipation), runs a one-step heuristic mission from each (``POST /missions``);
4. opens each mission in the dashboard in a real headless Chromium (Debian's ``chromium``, playwright) and
   writes ``<out>/candidates_<band>.png`` (the candidate cards: what the agent sees towards each
   candidate and what it anticipates there) and ``<out>/candidates_<band>_page.png`` (the whole page).

A person looks at these; nothing here scores them (bench.anticipation does).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from deploy.launcher import Launcher
from shared.logs import configure_logging
from shared.schemas import CameraIntrinsics, ViewPose

BANDS = (("near", 0.0, 1.0), ("mid", 1.0, 2.0), ("far", 2.0, 6.0))
CHROMIUM = "/usr/bin/chromium"


def say(msg: str) -> None:
    print(f"[cards {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def poses_by_band(scene: str, seed: int, tries: int = 400) -> dict[str, tuple[tuple[float, float, float], float]]:
    """One (floor position, heading) per band of true depth straight ahead (median of the central 9x9)."""
    from services.robot_io.core import ROBOTS

    out: dict[str, tuple[tuple[float, float, float], float]] = {}
    rng = np.random.default_rng(seed)
    with ROBOTS.create("sim", {"scene": scene}) as robot:
        cam = CameraIntrinsics(width_px=64, height_px=64)
        for _ in range(tries):
            p = robot.nav.sample_navigable(rng)
            h = float(rng.uniform(-math.pi, math.pi))
            pos = (float(p[0]), float(p[1]), float(p[2]))
            depth = robot.scene_views([ViewPose(position_m=pos, heading_rad=h)], cam, with_semantic=False).depth_m[0]
            centre = depth[28:37, 28:37]
            d = float(np.median(centre[centre > 0])) if (centre > 0).any() else math.inf
            for name, lo, hi in BANDS:
                if name not in out and lo <= d < hi:
                    out[name] = (pos, h)
            if len(out) == len(BANDS):
                break
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", type=Path, required=True, help="a PLY cloud of --scene (our layout)")
    ap.add_argument("--scene", default="generated:0")
    ap.add_argument("--seed", type=int, default=0, help="pose sampling seed")
    ap.add_argument("--run-dir", type=Path, default=Path("runs/cards"))
    ap.add_argument("--out", type=Path, default=Path("runs/screenshots"))
    args = ap.parse_args(argv)
    from playwright.sync_api import sync_playwright  # the dashboard tests' browser driver

    configure_logging("cards", "local", "WARNING")
    poses = poses_by_band(args.scene, args.seed)
    say(f"start poses by depth ahead: { {k: (tuple(round(c, 2) for c in p), round(h, 2)) for k, (p, h) in poses.items()} }")
    run_dir = args.run_dir.resolve()
    env = {"ANT_ROBOT_CONFIG": json.dumps({"scene": args.scene}), "ANT_STORE_DIR": str(run_dir / "maps"),
           "ANT_DB_PATH": str(run_dir / "gateway.sqlite3")}
    launcher = Launcher(run_dir, extra_env=env)
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        launcher.start(deadline_s=180)
        url = launcher.gateway_url
        with httpx.Client(base_url=url, timeout=300) as http:
            with open(args.map, "rb") as f:
                r = http.post("/maps", params={"map_id": "cards"}, content=f,
                              headers={"Content-Type": "application/octet-stream"})
            if r.status_code >= 300:
                raise RuntimeError(f"map import refused: {r.status_code} {r.text}")
            say(f"map imported: {http.get('/maps/cards').json()['point_count']:,} points")
            missions = {}
            for band, (pos, heading) in poses.items():
                body = {"instruction": "Walk forward and stop next to the sofa.", "map_id": "cards",
                        "options": {"policy": "heuristic", "max_steps": 1,
                                    "start_pose": {"position_m": list(pos), "heading_rad": heading}}}
                m = http.post("/missions", json=body).json()
                end = time.monotonic() + 300
                while http.get(f"/missions/{m['id']}").json()["state"] not in ("succeeded", "failed", "cancelled"):
                    if time.monotonic() > end:
                        raise RuntimeError(f"mission {m['id']} did not end")
                    time.sleep(0.5)
                missions[band] = m["id"]
                say(f"{band}: mission {m['id']} done")
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--headless", "--no-sandbox", "--disable-gpu"])
            try:
                for band, mid in missions.items():
                    page = browser.new_page(viewport={"width": 1440, "height": 1250})
                    page.goto(f"{url}/dashboard#{mid}")
                    page.wait_for_selector(".cand img", timeout=30_000)
                    page.wait_for_function(
                        "[...document.querySelectorAll('.cand img')].every(i => i.complete && i.naturalWidth > 0)",
                        timeout=30_000)
                    page.locator("#candidates").screenshot(path=str(args.out / f"candidates_{band}.png"))
                    page.screenshot(path=str(args.out / f"candidates_{band}_page.png"), full_page=True)
                    say(f"{band}: {args.out / f'candidates_{band}.png'}")
                    page.close()
            finally:
                browser.close()
    finally:
        launcher.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
