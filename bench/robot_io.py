"""Benchmark of the robot-io simulator: panorama rendering and move_to steps.

    python -m bench.robot_io [--repeats 30] [--threads 0]

Figures per scene: wall-clock median and best (the best is what an otherwise idle machine gives;
the median shows contention), and process CPU time per call (all threads). The panorama is 12
views of 256 x 256 (and of 64 x 64, the mapper's exploration size) RGB + depth + semantic labels at
HFOV 90 deg, rendered by each ray caster (SimConfig.ray_caster: Embree, and the z-buffer
rasteriser), the two calls alternating so both see the same load; then the rasteriser's figures
over Embree's. The agent turns 7 deg between calls so nothing could be served from a cache. The
nav grid's straight-line walk (the collision check of every move_to sub-step) is timed compiled and
as the array version it must equal.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from pathlib import Path

import numpy as np

from services.robot_io.core.raster import RasterScene
from services.robot_io.core.render import SceneRenderer
from services.robot_io.core.robot import SimConfig, SimRobot

DATA = Path(os.environ.get("ANT_SHARED_DATA") or Path(__file__).resolve().parents[1].parent / "shared" / "data")
REPLICA = DATA / "replica_office0" / "office0_mesh.ply"
CASTERS = ("embree", "raster")
HOUSE = "generated:0:area=200"


def _timed(fn, repeats: int) -> tuple[float, float, float]:
    """(median wall ms, best wall ms, mean CPU ms) over ``repeats`` calls after a warm-up call."""
    fn()  # warm-up: the first cast builds Embree's BVH, the first shade compiles the kernel
    walls, cpus = [], []
    for _ in range(repeats):
        c, t = time.process_time(), time.perf_counter()
        fn()
        walls.append((time.perf_counter() - t) * 1e3)
        cpus.append((time.process_time() - c) * 1e3)
    return statistics.median(walls), min(walls), statistics.fmean(cpus)


def _timed_alternating(fns: dict[str, object], repeats: int) -> dict[str, tuple[float, float, float]]:
    """:func:`_timed` for several functions, called in turn so that they share the same load."""
    for fn in fns.values():
        fn()
    walls: dict[str, list[float]] = {k: [] for k in fns}
    cpus: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            c, t = time.process_time(), time.perf_counter()
            fn()
            walls[name].append((time.perf_counter() - t) * 1e3)
            cpus[name].append((time.process_time() - c) * 1e3)
    return {k: (statistics.median(walls[k]), min(walls[k]), statistics.fmean(cpus[k])) for k in fns}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, default=0, help="Embree threads (0: all cores)")
    args = ap.parse_args(argv)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    rows = []
    scenes = [(f"house 200 m2 ({HOUSE})", HOUSE)]
    if REPLICA.is_file():
        scenes.append(("Replica office0", str(REPLICA)))
    for name, spec in scenes:
        t = time.perf_counter()
        robot = SimRobot(SimConfig(scene=spec, render_threads=args.threads, ray_caster="embree"))
        load_ms = (time.perf_counter() - t) * 1e3
        tris, walk = len(robot.scene.triangles), robot.nav.reachable_area_m2
        rows.append((f"{name}: load + nav grid ({tris} tris, {walk:.0f} m2 walkable)", load_ms, load_ms, float("nan")))
        t = time.perf_counter()
        RasterScene(robot.scene.vertices, robot.scene.triangles)  # what the first rasterised view builds
        raster_ms = (time.perf_counter() - t) * 1e3
        rows.append((f"{name}: rasteriser's scene preparation", raster_ms, raster_ms, float("nan")))
        renderers = {"embree": robot.renderer, "raster": SceneRenderer(robot.scene, args.threads, ray_caster="raster")}
        for size in (256, 64):  # 64: the size the mapper explores with (bench.mapper --size 64)
            cam = robot.camera.model_copy(update={"width_px": size, "height_px": size})

            def observe(caster: str, cam=cam):
                robot.renderer = renderers[caster]
                robot.turn(math.radians(7.0))
                robot.observe(cam)

            res = _timed_alternating({c: (lambda c=c: observe(c)) for c in CASTERS}, args.repeats)
            for c in CASTERS:
                rows.append((f"{name}: observe 12x{size}x{size} RGB-D-sem, {c}", *res[c]))
            ratio = [r / e for r, e in zip(res["raster"], res["embree"])]
            rows.append((f"{name}: observe 12x{size}x{size}, raster / embree (ratio, not ms)", *ratio))
        robot.renderer = renderers["embree"]
        rng = np.random.default_rng(0)
        robot.reset()

        def one_step():
            # One 0.25 m move_to step in a random direction (blocked moves cost the same checks).
            a = rng.uniform(-math.pi, math.pi)
            robot.move_to(0.25 * math.cos(a), 0.25 * math.sin(a))

        rows.append((f"{name}: move_to one 0.25 m step", *_timed(one_step, args.repeats * 5)))
        # NavGrid.walk, move_to's collision check (up to three per sub-step): compiled and array versions.
        starts = robot.nav.nodes_m[rng.integers(0, len(robot.nav.nodes_m), 64)]
        ends = starts + np.column_stack([0.25 * np.cos(a := rng.uniform(-math.pi, math.pi, 64)), 0.25 * np.sin(a), np.zeros(64)])
        for kernel in (True, False):
            robot.nav.use_kernel = kernel

            def walks():
                for p, q in zip(starts, ends):
                    robot.nav.walk(p, q)

            med, best, cpu = _timed(walks, args.repeats)
            label = "compiled" if kernel else "array version"
            # In microseconds (the columns' ms would round the compiled walk to 0.00).
            rows.append((f"{name}: nav walk 0.25 m, {label} (us per walk, not ms)", *(1e3 * v / 64 for v in (med, best, cpu))))
        robot.nav.use_kernel = True
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"robot-io simulator, {cores} cores available, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(f"{'benchmark':78s} {'median ms':>10s} {'best ms':>8s} {'cpu ms':>8s}")
    for n, m, b, c in rows:
        print(f"{n:78s} {m:10.2f} {b:8.2f} {c:8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
