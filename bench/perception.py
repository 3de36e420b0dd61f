"""Global perception per step (issues 20 and 21): the spatial map plus six anticipated views
(256x256, HFOV 90, visibility mode), on agent-built maps at the planner's real candidate poses and
on mesh-sampled buildings at room centres; wall and CPU time, points drawn, the one-pass floor,
and optionally the same steps rendered by another git revision of libs/pointrender in the same
process (same machine load for both: compare their ratio, not either figure alone).

    python -m bench.perception                                  # generated:0 rgbd map (~1 min)
    python -m bench.perception --against HEAD~3                 # + HEAD~3's renderer, interleaved
    python -m bench.perception --maps --scenes generated:0:area=100 generated:0:area=1000:floors=3

Columns: ``view ms`` the wall time of a step's six views on the renderer's two worker threads / 6
(as bench.renderer), ``view cpu`` their process CPU time / 6 (all threads: what an idle machine's
cores spend), ``x floor`` view ms over the floor (one pass over the cloud, bench.renderer), ``step``
the spatial map and the six views as the planner asks for them (the map drawn on a thread of its own
while the views render), wall and CPU, ``serial`` the same one after the other (wall), ``drawn`` the
points a view walks after culling and level of detail. Medians over steps. Agent-built maps come from
bench.anticipation's cache (built there the first time); sampled buildings are cached under
runs/perception.
"""

from __future__ import annotations

import argparse
import importlib
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.agent_maps import agent_map
from bench.renderer import _floor_ms, perception_step
from shared.geometry import PinholeCamera, camera_pose, rot_z
from shared.schemas import Candidate, Pose

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "runs" / "perception"
CAM = PinholeCamera(256, 256, 90.0)
CAMERA_HEIGHT_M = 1.25


def pointrender_at(rev: str):
    """libs.pointrender as it was at git revision ``rev``, imported under another name so that
    both versions live in one process (its own absolute imports renamed to match)."""
    sha = subprocess.check_output(["git", "rev-parse", "--short", rev], cwd=ROOT, text=True).strip()
    name = f"pointrender_{sha}"
    base = Path(tempfile.gettempdir()) / "bench-perception"
    if not (base / name).exists():
        tmp = Path(tempfile.mkdtemp(dir=base.parent))
        # The library lived in shared/pointrender before it moved to libs/pointrender (issue 31).
        where = next(d for d in ("libs/pointrender", "shared/pointrender")
                     if subprocess.run(["git", "cat-file", "-e", f"{sha}:{d}"], cwd=ROOT,
                                     stderr=subprocess.DEVNULL).returncode == 0)
        subprocess.run(f"git archive {sha} {where} | tar -x -C {tmp}", shell=True, check=True, cwd=ROOT)
        for f in (tmp / where).glob("*.py"):
            f.write_text(f.read_text().replace(where.replace("/", "."), name))
        base.mkdir(exist_ok=True)
        shutil.move(str(tmp / where), str(base / name))
        shutil.rmtree(tmp)
    if str(base) not in sys.path:
        sys.path.insert(0, str(base))
    return importlib.import_module(name)


def _sampled_building(spec: str, points_per_m2: float):
    """(cloud, steps) of a building's mesh sampled at ``points_per_m2``: six views 1 m from the
    centre of each of up to eight rooms (spread over the floors), facing outwards (as bench.renderer --scale)."""
    from services.renderer.tools import scenes
    from libs.world.scene import load_scene
    from shared.cloud import PointCloud

    sc = load_scene(spec)
    path = CACHE / f"{spec.replace(':', '_').replace('=', '-')}_{points_per_m2:g}.ply"
    if path.exists():
        cloud = PointCloud.load(path)
    else:
        tri = sc.vertices[sc.triangles]
        area = 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
        mesh = scenes.LabelledMesh(sc.vertices, sc.triangles, sc.vertex_colors.astype(np.float64),
                                   sc.triangle_labels, sc.label_names)
        cloud = scenes.sample_mesh(mesh, int(points_per_m2 * area))
        CACHE.mkdir(parents=True, exist_ok=True)
        cloud.save(path)
    rooms = [r for r in sc.rooms if r.room_type != "staircase"]
    steps = []
    for room in rooms[:: max(1, len(rooms) // 8)]:
        cx, cy = (room.min_xy_m[0] + room.max_xy_m[0]) / 2, (room.min_xy_m[1] + room.max_xy_m[1]) / 2
        heads = np.arange(6) * (math.pi / 3)
        steps.append([camera_pose((cx + math.cos(h), cy + math.sin(h), room.floor_z_m), float(h), 0.0, CAMERA_HEIGHT_M)
                      for h in heads])
    return cloud, steps


def _map_request(step: list[np.ndarray]):
    """The spatial map request of a step: the agent at the centre of its six views' floor points."""
    feet = np.array([p[:3, 3] - [0.0, 0.0, CAMERA_HEIGHT_M] for p in step])
    agent = feet.mean(axis=0)
    pose = Pose(position_m=tuple(float(v) for v in agent), heading_rad=0.0)
    cands = [Candidate(index=i, dx_m=float(f[0] - agent[0]), dy_m=float(f[1] - agent[1])) for i, f in enumerate(feet)]
    traj = np.array([agent - [1.0, 0.0, 0.0], agent])
    return pose, traj, cands


def run(name: str, cloud, steps, libs: dict, reps: int, configs: dict | None = None) -> None:
    """Time the steps with each renderer of ``libs`` (label -> a libs.pointrender module), each
    configured by ``configs[label]`` (default: the visibility mode), interleaved step by step."""
    from services.renderer.core import SpatialMapper

    floor = _floor_ms(cloud.xyz, rot_z(0.3).astype(np.float32))
    mapper = SpatialMapper()
    sides = {}
    for label, lib in libs.items():
        index = lib.IndexedCloud(cloud)
        renderer = lib.RENDERERS.create("numpy", (configs or {}).get(label, {"mode": "visibility"}))
        renderer.warm_up()
        t0 = time.perf_counter()
        renderer.prepare(index)  # per-map data: once per map version, at load
        prep_s = time.perf_counter() - t0
        sides[label] = (index, renderer, prep_s, {"view": [], "view_cpu": [], "step": [], "step_cpu": [], "serial": [],
                                                  "drawn": []})
    requests = [_map_request(s) for s in steps]
    for label, (index, renderer, _, _) in sides.items():  # first renders: per-floor grids, arrays
        for step, (pose, traj, cands) in zip(steps, requests):
            mapper.draw(index, pose, traj, cands, agent_up=True, size_px=512)
        renderer.render_poses(index, steps[0], CAM)
    for _ in range(reps):
        for step, (pose, traj, cands) in zip(steps, requests):
            for label, (index, renderer, _, m) in sides.items():
                t0, c0 = time.perf_counter(), time.process_time()
                out = renderer.render_poses(index, step, CAM)
                m["view"].append(1e3 * (time.perf_counter() - t0) / len(step))
                m["view_cpu"].append(1e3 * (time.process_time() - c0) / len(step))
                m["drawn"].extend(out.visible_points)
                t0, c0 = time.perf_counter(), time.process_time()
                perception_step(lambda: mapper.draw(index, pose, traj, cands, agent_up=True, size_px=512),  # noqa: B023
                                lambda: renderer.render_poses(index, step, CAM))  # noqa: B023
                m["step"].append(1e3 * (time.perf_counter() - t0))
                m["step_cpu"].append(1e3 * (time.process_time() - c0))
                t0 = time.perf_counter()
                mapper.draw(index, pose, traj, cands, agent_up=True, size_px=512)
                renderer.render_poses(index, step, CAM)
                m["serial"].append(1e3 * (time.perf_counter() - t0))
    print(f"\n== {name}: {len(cloud)} points, {len(steps)} steps x {reps}; floor (one pass over the cloud) "
          f"{floor:.2f} ms ==")
    print(f"{'renderer':<22} {'view ms':>8} {'view cpu':>9} {'x floor':>8} {'step ms':>8} {'step cpu':>9} "
          f"{'serial':>7} {'drawn':>8} {'prepare s':>9}   (targets: view <= 3x floor, step <= 20 ms)")
    for label, (_, _, prep_s, m) in sides.items():
        med = {k: float(np.median(v)) for k, v in m.items()}
        print(f"{label:<22} {med['view']:>8.2f} {med['view_cpu']:>9.2f} {med['view'] / floor:>8.2f} "
              f"{med['step']:>8.1f} {med['step_cpu']:>9.1f} {med['serial']:>7.1f} {int(med['drawn']):>8d} "
              f"{prep_s:>9.1f}")
    if len(sides) == 2:
        (ia, ra, _, ma), (ib, rb, _, mb) = sides.values()
        ratio = {k: float(np.median(mb[k]) / np.median(ma[k])) for k in ("view", "view_cpu", "step", "step_cpu")}
        line = (f"second / first: view {ratio['view']:.2f}, view cpu {ratio['view_cpu']:.2f}, "
                f"step {ratio['step']:.2f}, step cpu {ratio['step_cpu']:.2f}")
        if ra.config.mode == rb.config.mode:  # two revisions of one mode: did the change keep the images?
            a, b = ra.render_poses(ia, steps[0], CAM), rb.render_poses(ib, steps[0], CAM)
            same = all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("rgb", "depth_m", "hole_mask", "labels"))
            line += f"; first step's images identical: {same}"
        print(line)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", nargs="*", default=["rgbd"], help="agent-built maps of bench.anticipation (default rgbd)")
    ap.add_argument("--scenes", nargs="*", default=[], help="buildings sampled from their mesh, e.g. generated:0:area=1000:floors=3")
    ap.add_argument("--points-per-m2", type=float, default=400.0, help="--scenes: sampling density")
    ap.add_argument("--agents", type=int, default=16, help="agent poses whose candidates make the steps of a map")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--against", default=None, metavar="REV", help="also time libs/pointrender at this git revision")
    args = ap.parse_args(argv)
    import libs.pointrender as current

    libs = {"working tree": current}
    if args.against:
        libs = {f"at {args.against}": pointrender_at(args.against), **libs}
    for row in args.maps:
        spec, cloud, steps = agent_map(row, args.agents, seed=8)
        run(f"{spec} {row} map, candidate poses", cloud, steps, libs, args.reps)
    for spec in args.scenes:
        cloud, steps = _sampled_building(spec, args.points_per_m2)
        run(f"{spec}, mesh samples {args.points_per_m2:g}/m2, room centres", cloud, steps, libs, args.reps)


if __name__ == "__main__":
    main()
