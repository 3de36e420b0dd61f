"""Mapper benchmark: Algorithm 1 on generated houses (one and two floors).

    python -m bench.mapper [--scenes generated:0 generated:1:floors=2] [--size 96] [--json OUT]
                           [--predictor wide|cwp]
    python -m bench.mapper --scenes ../shared/data/replica_office0/office0_mesh.ply

Reports per scene: explored-node coverage of the simulator's reachable area (target >= 95 %),
hub visibility coverage per region (>= tau), exploration steps and moves, set cover + 2-opt
planning time (target < 1 s for a 200 m2 house) and the tour length against a plain
nearest-neighbour tour over the same hubs.
"""

from __future__ import annotations

import argparse
import json
import logging
import time

import numpy as np
from scipy.spatial import cKDTree

from shared.schemas import CameraIntrinsics

from services.mapper.core import DiscoveryConfig, NodeStatus, discover
from services.mapper.core.discovery import WIDE_EXPLORATION


def coverage_of(reachable_m: np.ndarray, nodes_m: np.ndarray, radius_m: float) -> float:
    """Fraction of reachable cells within ``radius_m`` (horizontal, same floor) of a node."""
    if len(nodes_m) == 0 or len(reachable_m) == 0:
        return 0.0
    scale = np.array([1.0, 1.0, 4.0])  # floors 2.5 m apart never match within a metre
    d, _ = cKDTree(nodes_m * scale).query(reachable_m * scale)
    return float((d <= radius_m).mean())


# Exploration predictor knobs: the wider DiscoveryConfig default, or the planner's CWP contract.
PREDICTOR_KNOBS = {"cwp": {}, "wide": WIDE_EXPLORATION}


def run_scene(scene: str, size_px: int, radius_m: float, predictor: str = "wide") -> dict:
    from services.robot_io.core.robot import ROBOTS

    cam = CameraIntrinsics(width_px=size_px, height_px=size_px, hfov_deg=90.0)
    robot = ROBOTS.create("sim", {"scene": scene, "camera": cam})
    cfg = DiscoveryConfig(predictor_config=PREDICTOR_KNOBS[predictor])
    t0 = time.perf_counter()
    d = discover(robot, cfg)
    wall = time.perf_counter() - t0
    nav = robot.nav
    reach = nav.nodes_m[nav.component == nav.main_component]
    g = d.result.graph
    visited = g.positions(g.nodes_with(NodeStatus.VISITED))
    explored = g.positions(g.nodes_with(NodeStatus.VISITED, NodeStatus.COVERED))
    regions = []
    for pt in d.tours:
        regions.append({
            "region": pt.tour.region,
            "hubs": len(pt.tour.hubs_m),
            "coverage": round(pt.tour.coverage, 3),
            "coverage_of_coverable": round(pt.tour.coverage / max(pt.achievable_coverage, 1e-9), 3),
            "achievable": round(pt.achievable_coverage, 3),
            "plan_s": round(pt.plan_s, 4),
            "tour_vs_nn": round(pt.order_length_m / pt.nn_length_m, 3) if pt.nn_length_m > 0 else 1.0,
            "path_m": round(pt.length_m, 1),
        })
    nn = sum(pt.nn_length_m for pt in d.tours)
    ours = sum(pt.order_length_m for pt in d.tours)
    return {
        "scene": scene,
        "predictor": predictor,
        "reachable_area_m2": round(nav.reachable_area_m2, 1),
        "floors": len(d.scene.floors),
        "stair_nodes": len(d.scene.stairs),
        "steps": d.result.steps,
        "moves": d.result.moves,
        "unreachable": d.result.unreachable,
        "finished": d.result.finished,
        f"coverage_visited_{radius_m:g}m": round(coverage_of(reach, visited, radius_m), 3),
        f"coverage_explored_{radius_m:g}m": round(coverage_of(reach, explored, radius_m), 3),
        "regions": len(d.tours),
        "min_hub_coverage": round(min((pt.tour.coverage for pt in d.tours), default=0.0), 3),
        "min_hub_coverage_of_coverable": round(min(
            (pt.tour.coverage / max(pt.achievable_coverage, 1e-9) for pt in d.tours), default=0.0), 3),
        "hubs": sum(len(pt.tour.hubs_m) for pt in d.tours),
        "max_region_plan_s": round(max((pt.plan_s for pt in d.tours), default=0.0), 3),
        "set_cover_2opt_s": round(d.timings_s["set_cover_2opt"], 3),
        "tour_vs_nn_ratio": round(ours / nn, 3) if nn > 0 else 1.0,
        "timings_s": {k: round(v, 2) for k, v in d.timings_s.items()},
        "wall_s": round(wall, 1),
        "per_region": regions,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["generated:0", "generated:1:floors=2"])
    ap.add_argument("--size", type=int, default=96, help="panorama view size in pixels")
    ap.add_argument("--radius", type=float, default=1.5, help="coverage radius around nodes (m)")
    ap.add_argument("--predictor", choices=sorted(PREDICTOR_KNOBS), default="wide",
                    help="exploration candidates: wide (10 at 15 deg, the default) or cwp (5 at 30 deg)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    rows = [run_scene(s, args.size, args.radius, args.predictor) for s in args.scenes]
    for r in rows:
        print(json.dumps({k: v for k, v in r.items() if k != "per_region"}))
        for reg in r["per_region"]:
            print("   ", json.dumps(reg))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
