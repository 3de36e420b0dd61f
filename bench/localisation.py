"""The mapper's online localisation against odometry drift (issue 33): explore and record the tours of
a scene with a drifting robot, the mapper's map <- odom correction off and on, side by side.

Printed per scene and drift scale (times the noisy row's drift of bench.agent_maps, with its depth
noise and holes): where each tour's first frame was recorded against where the robot truly stood
(median and max, position and heading), the regions skipped, the localiser's outcomes at the
exploration's panoramas, and the wall time of exploration plus tours. With ``--exact`` it also checks that a robot
without noise records the very same tours, bit for bit, with the correction on as off.

    python -m bench.localisation --scenes generated:0 generated:3:floors=2 --scales 0.5 1 2

No reconstruction here: the map built from these recordings is bench.anticipation's (drift-recon's
ladder); this isolates what the mapper hands it.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import time

import numpy as np

from bench.agent_maps import NOISY, _recording_truth
from shared.schemas import CameraIntrinsics

DRIFT_KEYS = ("odometry_drift_per_m", "heading_drift_per_rad")


def _noise(scale: float) -> dict:
    return {k: v * scale if k in DRIFT_KEYS else v for k, v in NOISY.items()}


def run(spec: str, noise: dict | None, localise: bool, size_px: int = 128, rate_hz: float = 4.0,
        localisation: dict | None = None) -> dict:
    """Explore ``spec`` and record its tours; the figures of one row (and the recordings' digest)."""
    from services.mapper.core import discover, discovery_config, execute_tours
    from services.robot_io.core.robot import ROBOTS

    cfg = {"scene": spec, "camera": CameraIntrinsics(width_px=size_px, height_px=size_px)}
    if noise:
        cfg["noise"] = noise
    robot = ROBOTS.create("sim", cfg)
    truth = _recording_truth(robot)
    dcfg = discovery_config("default", {"localisation": {**(localisation or {}), "enabled": localise}})
    t0 = time.perf_counter()
    d = discover(robot, dcfg)
    skipped: list[int] = []
    recs = execute_tours(robot, d.tours, d.scene, rate_hz=rate_hz, on_skip=lambda pt, e: skipped.append(pt.tour.region))
    wall = time.perf_counter() - t0
    loc = d.scene.localiser
    pos, head = [], []
    for rec in recs:
        f = rec.frames[0] if rec.frames else None
        if f is not None and f.index in truth:
            t = truth[f.index][0]
            pos.append(math.hypot(t.position_m[0] - f.pose.position_m[0], t.position_m[1] - f.pose.position_m[1]))
            head.append(abs(math.degrees(math.remainder(t.heading_rad - f.pose.heading_rad, 2 * math.pi))))
    digest = hashlib.sha256()
    for rec in recs:
        digest.update(repr((rec.region, rec.start_pose.position_m, rec.start_pose.heading_rad)).encode())
        for f in rec.frames:
            digest.update(repr((f.index, f.timestamp_s, f.pose.position_m, f.pose.heading_rad, f.imu_heading_rad)).encode())
            digest.update(np.ascontiguousarray(f.rgb).tobytes())
    robot.close()
    return {"spec": spec, "localise": localise, "tours": len(d.tours), "skipped": len(skipped),
            "start_pos_m": pos, "start_head_deg": head, "wall_s": wall, "panoramas": d.result.steps,
            "report": loc.report() if loc is not None else None, "digest": digest.hexdigest()[:16]}


def _row(r: dict) -> str:
    p, h = np.asarray(r["start_pos_m"]), np.asarray(r["start_head_deg"])
    rep = r["report"]
    outcomes = ", ".join(f"{k} {v}" for k, v in rep["outcomes"].items()) if rep else "off"
    return (f"| {'on' if r['localise'] else 'off'} | {np.median(p):.3f} | {p.max():.3f} | {np.median(h):.2f} | "
            f"{h.max():.2f} | {r['skipped']}/{r['tours']} | {r['panoramas']} | {r['wall_s']:.0f} | {outcomes} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["generated:0"])
    ap.add_argument("--scales", nargs="+", type=float, default=[1.0], help="times the noisy row's drift")
    ap.add_argument("--exact", action="store_true", help="also check that noise-free tours are bit-identical")
    args = ap.parse_args()
    for spec in args.scenes:
        if args.exact:
            off, on = run(spec, None, False), run(spec, None, True)
            same = off["digest"] == on["digest"]
            print(f"{spec} noise-free: recordings {'bit-identical' if same else 'DIFFER'} with the correction on "
                  f"({off['digest']} / {on['digest']}); wall {off['wall_s']:.0f} s off, {on['wall_s']:.0f} s on "
                  f"({on['wall_s'] / off['wall_s']:.2f}x)", flush=True)
        for scale in args.scales:
            print(f"\n{spec}, drift x{scale:g} ({NOISY['odometry_drift_per_m'] * scale:g} m/sqrt(m), "
                  f"{NOISY['heading_drift_per_rad'] * scale:g} rad/sqrt(rad)), depth noise and holes", flush=True)
            print("| correction | tour start median m | max m | heading median deg | max deg | skipped | "
                  "panoramas | wall s | panoramas placed |")
            print("|---|---|---|---|---|---|---|---|---|")
            rows = [run(spec, _noise(scale), False), run(spec, _noise(scale), True)]
            for r in rows:
                print(_row(r), flush=True)
            print(f"wall time with the correction: {rows[1]['wall_s'] / rows[0]['wall_s']:.2f}x", flush=True)


if __name__ == "__main__":
    main()
