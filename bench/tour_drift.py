"""Where a drifting robot's tour frames go wrong (issue 33): per recorded tour frame, the error of the
pose the map uses (the frame's pose after the mapper's correction) against the simulator's true pose,
grouped by the odometry path driven since the last fix (a panorama or, with frame registration, a
frame placed by registration).

    python -m bench.tour_drift                        # generated:0, the noisy row's drift x 1
    python -m bench.tour_drift --frames on            # the same, tour frames registered
    python -m bench.tour_drift --drift-scale 0        # depth noise and holes alone (poses exact)
    python -m bench.tour_drift --drift-scale -1       # a noise-free robot (nothing may move)
    python -m bench.tour_drift --band median          # the scan's height band by each column's median range
    python -m bench.tour_drift --graph off            # the sequential localiser alone (no pose graph)

Explores once and drives the tours (no reconstruction): about a minute of CPU on generated:0.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from bench.agent_maps import _recording_truth, noise_config, tap_true_poses

BINS_M = (0.0, 0.25, 0.5, 1.0, 2.0, math.inf)


def run(spec: str, drift_scale: float, frames: bool, size_px: int = 128, rate_hz: float = 4.0,
        band_from_median: bool = False, graph: bool = True) -> dict:
    from services.mapper.core import discover, discovery_config, execute_tours
    from services.robot_io.core.robot import ROBOTS
    from shared.schemas import CameraIntrinsics

    robot_cfg = {"scene": spec, "camera": CameraIntrinsics(width_px=size_px, height_px=size_px)}
    if drift_scale >= 0:  # negative: a noise-free robot (exact depth and poses)
        robot_cfg["noise"] = noise_config("noisy", drift_scale)
    robot = ROBOTS.create("sim", robot_cfg)
    truth = _recording_truth(robot)
    # panorama timestamp -> (the true pose it was taken at, its odometry pose)
    pano_truth = tap_true_poses(robot, "observe", lambda pano: pano.timestamp_s)
    cfg = discovery_config("default")
    cfg.localisation.frames.enabled = frames
    cfg.localisation.band_from_median = band_from_median
    cfg.localisation.graph.enabled = graph
    c0 = time.process_time()
    d = discover(robot, cfg)
    c1 = time.process_time()
    recs = execute_tours(robot, d.tours, d.scene, rate_hz=rate_hz)
    c2 = time.process_time()
    loc = d.scene.localiser
    fixes = sorted([s.timestamp_s for s in loc.steps if not s.outcome.startswith("odometry")]
                   + [s.timestamp_s for s in loc.frame_steps if not s.outcome.startswith("odometry")])
    rows = []  # (path since fix m, turn since fix deg, position error m, heading error deg)
    for rec in recs:
        frames_ = [f for f in rec.frames if f.index in truth]
        path_m, turn_rad, prev = 0.0, 0.0, None
        for f in frames_:
            odo = truth[f.index][1]
            if prev is not None:
                path_m += float(np.hypot(*np.subtract(odo.position_m[:2], prev.position_m[:2])))
                turn_rad += abs(math.remainder(odo.heading_rad - prev.heading_rad, 2 * math.pi))
            prev = odo
            k = np.searchsorted(fixes, f.timestamp_s, side="right")
            last = fixes[k - 1] if k else -math.inf
            if not rows or rows[-1][4] != last or rows[-1][5] != rec.region:
                base = (path_m, turn_rad)  # the first frame after a fix (or a tour's start) starts the count
            true = truth[f.index][0]
            rows.append((path_m - base[0], math.degrees(turn_rad - base[1]),
                         float(np.hypot(*np.subtract(true.position_m[:2], f.pose.position_m[:2]))),
                         abs(math.degrees(math.remainder(true.heading_rad - f.pose.heading_rad, 2 * math.pi))),
                         last, rec.region))
    a = np.array([r[:4] for r in rows]) if rows else np.zeros((0, 4))
    # Each panorama's pose after its own step (what the model took it at) against the truth, with
    # the odometry path from the start: an error that grows with it is the model's own drift.
    panos, path_m, prev = [], 0.0, None
    for st in loc.steps:
        if prev is not None:
            path_m += float(np.hypot(*np.subtract(st.odom.position_m[:2], prev.position_m[:2])))
        prev = st.odom
        true = pano_truth.get(st.timestamp_s, (None,))[0]
        if true is not None:
            placed = st.correction.pose(st.odom)
            panos.append((path_m, float(np.hypot(*np.subtract(true.position_m[:2], placed.position_m[:2]))),
                          abs(math.degrees(math.remainder(true.heading_rad - placed.heading_rad, 2 * math.pi))),
                          float(np.hypot(*np.subtract(true.position_m[:2], st.odom.position_m[:2]))),
                          not st.outcome.startswith("odometry")))
    outcomes: dict[str, int] = {}
    for s in loc.frame_steps:
        key = s.outcome.split(":")[0]
        outcomes[key] = outcomes.get(key, 0) + 1
    robot.close()
    return {"errors": a, "explore_cpu_s": c1 - c0, "tours_cpu_s": c2 - c1, "frame_outcomes": outcomes,
            "panoramas": loc.report()["outcomes"], "frames": len(a), "graph": loc.report().get("graph"),
            "pano_errors": np.array(panos) if panos else np.zeros((0, 5))}


def report(r: dict) -> None:
    a = r["errors"]
    print(f"   {r['frames']} tour frames; CPU explore {r['explore_cpu_s']:.1f} s, tours {r['tours_cpu_s']:.1f} s; "
          f"panoramas {r['panoramas']}; frames registered {r['frame_outcomes']}")
    if r.get("graph"):
        print(f"   pose graph (last solve): {r['graph']}")
    print("   | path since fix | frames | pos median / p90 / max (cm) | heading median / p90 (deg) "
          "| turn median (deg) |")
    print("   |---|---|---|---|---|")
    rows = [(f"{lo:g}-{hi:g} m", (a[:, 0] >= lo) & (a[:, 0] < hi)) for lo, hi in zip(BINS_M[:-1], BINS_M[1:])]
    for name, m in rows + [("all", np.ones(len(a), bool))]:
        if not m.any():
            continue
        e = a[m]
        pos = 100 * e[:, 2]
        print(f"   | {name} | {int(m.sum())} | {np.median(pos):.1f} / {np.percentile(pos, 90):.1f} / {pos.max():.1f} | "
              f"{np.median(e[:, 3]):.2f} / {np.percentile(e[:, 3], 90):.2f} | {np.median(e[:, 1]):.0f} |")
    p = r["pano_errors"]
    if len(p):
        print("   panoramas (the model's poses) by odometry path from the start:")
        print("   | path from start | panoramas | placed | pos median / p90 (cm) | heading median (deg) "
              "| odometry pos median (cm) |")
        print("   |---|---|---|---|---|---|")
        edges = np.quantile(p[:, 0], [0, 0.25, 0.5, 0.75, 1.0])
        for lo, hi in zip(edges[:-1], edges[1:]):
            e = p[(p[:, 0] >= lo) & (p[:, 0] <= hi)]
            if not len(e):
                continue
            print(f"   | {lo:.0f}-{hi:.0f} m | {len(e)} | {int(e[:, 4].sum())} | {100 * np.median(e[:, 1]):.1f} / "
                  f"{100 * np.percentile(e[:, 1], 90):.1f} | {np.median(e[:, 2]):.2f} | "
                  f"{100 * np.median(e[:, 3]):.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="generated:0")
    ap.add_argument("--drift-scale", type=float, default=1.0)
    ap.add_argument("--frames", choices=("on", "off"), default="off", help="register tour frames (issue 33)")
    ap.add_argument("--graph", choices=("on", "off"), default="on", help="the panoramas' pose graph (posegraph.py)")
    ap.add_argument("--band", choices=("median", "pixel"), default="pixel",
                    help="scan height band chosen by each column's median range, or by each pixel's own depth")
    args = ap.parse_args()
    print(f"## {args.scene}, drift x{args.drift_scale:g}, frame registration {args.frames}, band by {args.band}, "
          f"pose graph {args.graph}")
    report(run(args.scene, args.drift_scale, args.frames == "on", band_from_median=args.band == "median",
               graph=args.graph == "on"))


if __name__ == "__main__":
    main()
