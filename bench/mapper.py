"""Mapper benchmark: Algorithm 1 on generated houses, one scene at a time or as a scale ladder.

    python -m bench.mapper [--scenes generated:0 generated:1:floors=2] [--size 96] [--json OUT]
                           [--predictor wide|cwp]
    python -m bench.mapper --scenes ../shared/data/replica_office0/office0_mesh.ply
    python -m bench.mapper --ladder [--full] [--jobs 2] [--size 64] [--json OUT]
    python -m bench.mapper --ladder --rungs 200x3 1000x1 --seeds 2 --rows ROWS.jsonl
    python -m bench.mapper --scenes generated:0:area=1000 --save-exploration DIR
    python -m bench.mapper --scenes generated:2013:floors=2 --size 128 --noise noisy --noise-seeds 0 1 2
    python -m bench.mapper --replan DIR/*.pkl [--repeat 3]

Reports per scene: explored-node coverage of the simulator's reachable area (target >= 95 %),
hub visibility coverage per region (>= tau), exploration steps and moves, set cover + 2-opt
planning time and the tour length against a plain nearest-neighbour tour over the same hubs.

The ladder (issue 21) runs 100 / 200 / 500 / 1,000 m2 by 1 / 2 / 3 floors, 5 seeds each with
``--full`` (60 explorations), or a quick subset by default (seed 0 of 100 / 500 / 1,000 m2 by 1 and
3 floors). Per rung it prints coverage, floors reached, steps, moves, metres walked per m2, wall
seconds of explore (split into the robot's time - rendering and moving in the simulator - and the
mapper's own), analyse and plan, and set cover + 2-opt; then a least-squares fit of each cost
against the reachable area, ``cost ~ area^k``, and the issue's targets met or not:
coverage >= 95 % on every rung; explore + plan <= 30 s wall at 1,000 m2 (simulator included); set cover
+ 2-opt <= 2 s at 1,000 m2; tours no longer than a nearest-neighbour tour over the same hubs.

``--noise noisy`` explores each scene again with the robot's sensor noise (bench.agent_maps' rows: depth noise
and holes, odometry drift), once per ``--noise-seeds``, and prints the noisy explorations against the
noise-free one (floors reached, coverage), since a noisy robot that misses a floor still ends "finished".

``--save-exploration`` keeps each scene's exploration (a pickle, local files only); ``--replan``
runs analyse and plan again on saved explorations, so planning can be timed and profiled without
exploring again (and two versions of the planner compared on the same graph).
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


class TimedRobot:
    """The simulator behind a stopwatch: how much of the exploration's wall (and process CPU) time
    is the robot's; ``observe_s`` / ``observe_cpu_s`` the panoramas' share of it."""

    def __init__(self, robot):
        self.robot = robot
        self.robot_s = self.robot_cpu_s = self.observe_s = self.observe_cpu_s = 0.0

    def __getattr__(self, name):
        # The rest of the robot as it is (a drifting robot's localiser reads its pose and odometry).
        if name == "robot":  # not set yet (a copy being built): no recursion through ourselves
            raise AttributeError(name)
        return getattr(self.robot, name)

    def observe(self):
        t, c = time.perf_counter(), time.process_time()
        try:
            return self.robot.observe()
        finally:
            self.robot_s += (dt := time.perf_counter() - t)
            self.robot_cpu_s += (dc := time.process_time() - c)
            self.observe_s += dt
            self.observe_cpu_s += dc

    def move_to(self, dx_m: float, dy_m: float):
        t, c = time.perf_counter(), time.process_time()
        try:
            return self.robot.move_to(dx_m, dy_m)
        finally:
            self.robot_s += time.perf_counter() - t
            self.robot_cpu_s += time.process_time() - c


def floors_reached(scene, visited_m: np.ndarray) -> int:
    """Storeys of a generated house with at least a few visited nodes on their floor."""
    levels = sorted({r.floor_z_m for r in scene.rooms if r.room_type != "staircase"})
    return sum(int(np.sum(np.abs(visited_m[:, 2] - z) < 0.1) >= 3) for z in levels) if len(visited_m) else 0


def coverage_per_floor(scene, reachable_m: np.ndarray, nodes_m: np.ndarray, radius_m: float) -> list[float]:
    """``coverage_of`` on each storey of a generated house (its stairwells with the storey below)."""
    levels = sorted({r.floor_z_m for r in scene.rooms if r.room_type != "staircase"})
    out = []
    for k, z in enumerate(levels):
        top = levels[k + 1] - 0.1 if k + 1 < len(levels) else np.inf
        on = (reachable_m[:, 2] > z - 0.1) & (reachable_m[:, 2] < top)
        out.append(round(coverage_of(reachable_m[on], nodes_m, radius_m), 3))
    return out


def replan(path: str, repeat: int) -> dict:
    """Analyse + plan on a saved exploration; the best of ``repeat`` runs (the machine may be busy)."""
    import pickle

    from services.mapper.core.regions import RegionConfig, analyse
    from services.mapper.core.tours import TourConfig, TourPlanner

    with open(path, "rb") as f:
        result = pickle.load(f)
    best: dict = {}
    for _ in range(repeat):
        t0 = time.perf_counter()
        scene = analyse(result, RegionConfig())
        t1 = time.perf_counter()
        tours = TourPlanner(TourConfig()).plan(scene)
        t2 = time.perf_counter()
        nn = sum(pt.nn_length_m for pt in tours)
        row = {"exploration": path, "analyse_s": round(t1 - t0, 2), "plan_s": round(t2 - t1, 2),
               "set_cover_2opt_s": round(sum(pt.plan_s for pt in tours), 3), "regions": len(tours),
               "hubs": sum(len(pt.tour.hubs_m) for pt in tours),
               "tour_vs_nn_ratio": round(sum(pt.order_length_m for pt in tours) / nn, 4) if nn > 0 else 1.0,
               "min_hub_coverage": round(min((pt.tour.coverage for pt in tours), default=0.0), 3)}
        if not best or row["plan_s"] + row["analyse_s"] < best["plan_s"] + best["analyse_s"]:
            best = row
    return best


def run_scene(scene: str, size_px: int, radius_m: float, predictor: str = "wide",
              save_dir: str | None = None, ray_caster: str = "auto", noise: str | None = None,
              noise_seed: int = 0) -> dict:
    from services.robot_io.core.robot import ROBOTS

    cam = CameraIntrinsics(width_px=size_px, height_px=size_px, hfov_deg=90.0)
    robot_cfg = {"scene": scene, "camera": cam, "ray_caster": ray_caster}
    if noise:
        from bench.agent_maps import noise_config

        robot_cfg["noise"] = noise_config(noise, 1.0, noise_seed)
    robot = ROBOTS.create("sim", robot_cfg)
    timed = TimedRobot(robot)
    cfg = DiscoveryConfig(predictor_config=PREDICTOR_KNOBS[predictor])
    t0, c0 = time.perf_counter(), time.process_time()
    d = discover(timed, cfg)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if save_dir:
        import pickle
        from pathlib import Path

        Path(save_dir).mkdir(parents=True, exist_ok=True)
        name = scene.replace(":", "_").replace("/", "_") + (f"_{noise}_seed{noise_seed}" if noise else "")
        with open(Path(save_dir) / (name + ".pkl"), "wb") as f:
            pickle.dump(d.result, f)
    nav = robot.nav
    reach = nav.nodes_m[nav.component == nav.main_component]
    g = d.result.graph
    # A drifting robot's nodes sit where it believed it stood: centimetres off after the pose graph,
    # against the 1.5 m coverage radius.
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
            "paths_on": pt.paths_on,
        })
    nn = sum(pt.nn_length_m for pt in d.tours)
    ours = sum(pt.order_length_m for pt in d.tours)
    traj = d.result.trajectory_m
    walked = float(np.linalg.norm(np.diff(traj, axis=0), axis=1).sum()) if len(traj) > 1 else 0.0
    return {
        "scene": scene,
        "predictor": predictor,
        "noise": noise or "none",
        "noise_seed": noise_seed if noise else None,
        "reachable_area_m2": round(nav.reachable_area_m2, 1),
        "floors": len(d.scene.floors),
        "scene_floors": robot.scene.floors,
        "floors_reached": floors_reached(robot.scene, visited),
        "coverage_per_floor": coverage_per_floor(robot.scene, reach, visited, radius_m),
        "stair_nodes": len(d.scene.stairs),
        "steps": d.result.steps,
        "moves": d.result.moves,
        "walked_m": round(walked, 1),
        "walked_m_per_m2": round(walked / max(nav.reachable_area_m2, 1e-9), 3),
        "unreachable": d.result.unreachable,
        "finished": d.result.finished,
        "outcome": d.result.summary(),
        "ray_caster": robot.renderer.caster_for(size_px, size_px),
        "robot_s": round(timed.robot_s, 2),
        "robot_cpu_s": round(timed.robot_cpu_s, 2),
        "observe_s": round(timed.observe_s, 2),
        "observe_cpu_s": round(timed.observe_cpu_s, 2),
        "mapper_explore_s": round(d.timings_s["explore"] - timed.robot_s, 2),
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
        "cpu_s": round(cpu, 1),
        "per_region": regions,
    }


def print_noise_table(rows: list[dict], radius_m: float) -> None:
    """Per scene, the noise-free exploration against each noisy one: floors reached, coverage (per floor),
    panoramas and regions. A noisy robot whose depth closes a doorway or hides a flight explores less
    and still reports itself finished (its own map has no frontier left): only the simulator's
    reachable area shows what it missed."""
    key = f"coverage_visited_{radius_m:g}m"
    print(f"\n{'scene':<26} {'noise':<12} {'floors':>6} {'coverage':>8}  {'per floor':<16} {'steps':>5} "
          f"{'regions':>7} {'finished':>8}")
    for r in rows:
        tag = "none" if r["noise"] == "none" else f"{r['noise']} s{r['noise_seed']}"
        print(f"{r['scene']:<26} {tag:<12} {r['floors_reached']:>3}/{r['scene_floors']:<2} {100 * r[key]:>7.1f}%  "
              f"{str([round(100 * c, 1) for c in r['coverage_per_floor']]):<16} {r['steps']:>5} {r['regions']:>7} "
              f"{str(r['finished']):>8}")
    for scene in dict.fromkeys(r["scene"] for r in rows):
        base = next(r for r in rows if r["scene"] == scene and r["noise"] == "none")
        noisy = [r for r in rows if r["scene"] == scene and r["noise"] != "none"]
        lost = [r["noise_seed"] for r in noisy if r["floors_reached"] < base["floors_reached"]]
        print(f"mapper noise {scene}: coverage {100 * base[key]:.1f}% noise-free, "
              f"{' / '.join(f'{100 * r[key]:.1f}' for r in noisy)}% noisy; seeds short of a floor: {lost or 'none'}")


LADDER_AREAS = (100, 200, 500, 1000)
LADDER_FLOORS = (1, 2, 3)
LADDER_SEEDS = 5
QUICK = [(100, 1), (100, 3), (500, 1), (500, 3), (1000, 1), (1000, 3)]


def ladder_specs(full: bool, rungs: list[tuple[int, int]] | None = None,
                 seeds: int | None = None) -> list[tuple[int, int, int, str]]:
    """(area, floors, seed, scene) to explore: the whole ladder, the quick subset, or ``rungs``
    (area, floors) given by hand, with ``seeds`` seeds each (5 full, 1 quick by default)."""
    if rungs is None:
        rungs = [(a, f) for a in LADDER_AREAS for f in LADDER_FLOORS] if full else QUICK
    seeds = range(seeds if seeds is not None else (LADDER_SEEDS if full else 1))
    # Seed by seed, so that a ladder cut short still has every rung measured.
    return [(a, f, s, f"generated:{s}:area={a}:floors={f}") for s in seeds for a, f in rungs]


def _ladder_job(args) -> dict:
    area, floors, seed, spec, size, radius = args
    logging.basicConfig(level=logging.ERROR)
    row = run_scene(spec, size, radius)
    row.update(area_m2=area, scene_floors=floors, seed=seed)
    return row


def growth_exponent(x: np.ndarray, y: np.ndarray) -> float:
    """k of the least-squares fit log y = k log x + c (NaN with fewer than two distinct x)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = (x > 0) & (y > 0)
    if len(np.unique(x[ok])) < 2:
        return float("nan")
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])


LADDER_COSTS = ("steps", "moves", "walked_m", "explore_s", "robot_s", "mapper_explore_s", "analyse_s",
                "plan_s", "set_cover_2opt_s")


def _flat(row: dict, radius_m: float) -> dict:
    t = row["timings_s"]
    return {**row, "coverage": row[f"coverage_visited_{radius_m:g}m"], "explore_s": t["explore"],
            "analyse_s": t["analyse"], "plan_s": t["plan"]}


def print_ladder(rows: list[dict], radius_m: float) -> dict:
    rows = [_flat(r, radius_m) for r in rows]
    head = ("rung", "n", "reach m2", "coverage min/mean", "estimate min", "floors", "steps", "moves", "m/m2",
            "explore s (robot+mapper)", "analyse s", "plan s", "cover+2opt s", "tour/NN max")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    rungs = sorted({(r["area_m2"], r["scene_floors"]) for r in rows})
    for area, fl in rungs:
        rr = [r for r in rows if r["area_m2"] == area and r["scene_floors"] == fl]
        m = lambda k: float(np.mean([r[k] for r in rr]))  # noqa: E731
        cov = [r["coverage"] for r in rr]
        reached = f"{min(r['floors_reached'] for r in rr)}-{max(r['floors_reached'] for r in rr)}/{fl}"
        est = min(r["outcome"]["coverage_estimate"] for r in rr)
        print(f"| {area} m2 x {fl} | {len(rr)} | {m('reachable_area_m2'):.0f} | {min(cov):.1%} / {np.mean(cov):.1%} "
              f"| {est:.1%} | {reached} | {m('steps'):.0f} | {m('moves'):.0f} | {m('walked_m_per_m2'):.2f} "
              f"| {m('explore_s'):.1f} ({m('robot_s'):.1f}+{m('mapper_explore_s'):.1f}) | {m('analyse_s'):.2f} "
              f"| {m('plan_s'):.2f} | {m('set_cover_2opt_s'):.2f} | {max(r['tour_vs_nn_ratio'] for r in rr):.3f} |")
    area = np.array([r["reachable_area_m2"] for r in rows])
    exps = {k: round(growth_exponent(area, np.array([r[k] for r in rows])), 2) for k in LADDER_COSTS}
    print("\ngrowth exponents vs reachable area (cost ~ area^k, all runs):")
    print("  " + ", ".join(f"{k} {v}" for k, v in exps.items()))
    big = [r for r in rows if r["area_m2"] == max(LADDER_AREAS)]
    targets = {
        "coverage >= 95 % on every rung": all(r["coverage"] >= 0.95 for r in rows),
        "every floor reached": all(r["floors_reached"] == r["scene_floors"] for r in rows),
        # The figure is the wall time of the whole exploration, simulator included: the robot's
        # share is printed beside it, not subtracted from it.
        "explore + plan <= 30 s wall at 1,000 m2": bool(big) and max(
            r["explore_s"] + r["plan_s"] for r in big) <= 30.0,
        "set cover + 2-opt <= 2 s at 1,000 m2": bool(big) and max(r["set_cover_2opt_s"] for r in big) <= 2.0,
        "tours no longer than nearest neighbour": all(r["tour_vs_nn_ratio"] <= 1.0 + 1e-9 for r in rows),
    }
    if big:
        print(f"  at 1,000 m2: explore + plan wall {max(r['explore_s'] + r['plan_s'] for r in big):.1f} s max "
              f"(robot {max(r['robot_s'] for r in big):.1f} s of it; the mapper's own explore + plan "
              f"{max(r['mapper_explore_s'] + r['plan_s'] for r in big):.1f} s max)")
    print("targets:")
    for k, ok in targets.items():
        print(f"  [{'x' if ok else ' '}] {k}")
    return {"exponents": exps, "targets": targets}


def run_ladder(full: bool, jobs: int, size_px: int, radius_m: float, out_json: str | None,
               rows_path: str | None = None, rungs: list[tuple[int, int]] | None = None,
               seeds: int | None = None) -> None:
    specs = ladder_specs(full, rungs, seeds)
    args = [(a, f, s, spec, size_px, radius_m) for a, f, s, spec in specs]
    rows: list[dict] = []
    t0 = time.perf_counter()

    def done(row: dict) -> None:
        rows.append(row)
        _progress(row, t0, radius_m, len(args), len(rows))
        if rows_path:  # one JSON line per exploration: a ladder cut short can still be tabled
            with open(rows_path, "a") as f:
                f.write(json.dumps({k: v for k, v in row.items() if k != "per_region"}) + "\n")

    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs) as pool:
            for row in pool.map(_ladder_job, args):
                done(row)
    else:
        for a in args:
            done(_ladder_job(a))
    summary = print_ladder(rows, radius_m)
    if out_json:
        with open(out_json, "w") as f:
            json.dump({"rows": rows, **summary}, f, indent=2)


def _progress(row: dict, t0: float, radius_m: float, total: int, done: int) -> None:
    print(f"[{done}/{total} {time.perf_counter() - t0:.0f} s] {row['scene']}: reach {row['reachable_area_m2']} m2, "
          f"coverage {row[f'coverage_visited_{radius_m:g}m']:.1%}, floors {row['floors_reached']}/{row['scene_floors']}, "
          f"{row['steps']} steps, {row['outcome']['stop_reason']}, explore {row['timings_s']['explore']} s "
          f"(robot {row['robot_s']} s)", flush=True)


def main() -> None:
    from bench.agent_maps import NOISE  # here, not at the top: the ladder's job processes never parse arguments

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["generated:0", "generated:1:floors=2"])
    ap.add_argument("--size", type=int, default=None,
                    help="panorama view size in pixels (96 for scenes, 64 for the ladder)")
    ap.add_argument("--radius", type=float, default=1.5, help="coverage radius around nodes (m)")
    ap.add_argument("--predictor", choices=sorted(PREDICTOR_KNOBS), default="wide",
                    help="exploration candidates: wide (10 at 15 deg, the default) or cwp (5 at 30 deg)")
    ap.add_argument("--ladder", action="store_true", help="the scale ladder instead of --scenes")
    ap.add_argument("--full", action="store_true", help="the whole ladder: 12 rungs x 5 seeds")
    ap.add_argument("--jobs", type=int, default=1, help="explorations run in parallel processes")
    ap.add_argument("--rungs", nargs="+", default=None, metavar="AREAxFLOORS",
                    help="ladder: only these rungs, e.g. 200x3 1000x1")
    ap.add_argument("--seeds", type=int, default=None, help="ladder: seeds per rung (5 with --full, else 1)")
    ap.add_argument("--rows", default=None, help="ladder: append one JSON line per exploration here")
    ap.add_argument("--table", default=None, help="ladder: print the table of a --rows file and exit")
    ap.add_argument("--noise", choices=sorted(NOISE), default=None,
                    help="--scenes: also explore with this sensor noise (bench.agent_maps' rows), once per seed")
    ap.add_argument("--noise-seeds", type=int, nargs="+", default=[0], help="--noise: the simulator's noise seeds")
    ap.add_argument("--json", default=None)
    ap.add_argument("--save-exploration", default=None, help="--scenes: pickle each exploration into this folder")
    ap.add_argument("--replan", nargs="+", default=None, help="analyse + plan again on saved explorations")
    ap.add_argument("--repeat", type=int, default=1, help="--replan: best of this many runs")
    ap.add_argument("--ray-caster", choices=["auto", "embree", "raster"], default="auto",
                    help="--scenes: what renders the simulator's panoramas (SimConfig.ray_caster)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    if args.noise and (args.ladder or args.replan or args.table):
        ap.error("--noise explores --scenes")
    if args.noise and (len(set(args.noise_seeds)) != len(args.noise_seeds) or min(args.noise_seeds) < 0):
        ap.error(f"--noise-seeds: non-negative and each once, got {args.noise_seeds}")
    if args.replan:
        for path in args.replan:
            print(json.dumps(replan(path, args.repeat)), flush=True)
        return
    if args.table:
        with open(args.table) as f:
            print_ladder([json.loads(line) for line in f if line.strip()], args.radius)
        return
    if args.ladder:
        rungs = None
        if args.rungs:
            try:
                rungs = [tuple(int(v) for v in r.lower().split("x")) for r in args.rungs]
            except ValueError:
                ap.error("--rungs takes AREAxFLOORS, e.g. 200x3")
            if any(len(r) != 2 or r[0] <= 0 or not 1 <= r[1] <= 3 for r in rungs):
                ap.error("--rungs takes AREAxFLOORS with 1 to 3 floors, e.g. 200x3")
        run_ladder(args.full, args.jobs, args.size or 64, args.radius, args.json, args.rows, rungs, args.seeds)
        return
    runs = [(None, 0)] + ([(args.noise, seed) for seed in args.noise_seeds] if args.noise else [])
    rows = [run_scene(s, args.size or 96, args.radius, args.predictor, args.save_exploration, args.ray_caster,
                      noise, seed) for s in args.scenes for noise, seed in runs]
    for r in rows:
        print(json.dumps({k: v for k, v in r.items() if k != "per_region"}))
        for reg in r["per_region"]:
            print("   ", json.dumps(reg))
    if args.noise:
        print_noise_table(rows, args.radius)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
