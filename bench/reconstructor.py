"""Reconstructor benchmark (issue 5): grounding error, map accuracy, RGB-D throughput, Replica.

    python -m bench.reconstructor [--houses generated:3:area=50 ...] [--size 96] [--seeds 0 1 2]
                                  [--throughput-size 256] [--no-throughput] [--no-replica] [--json OUT]
    python -m bench.reconstructor --building [generated:0:area=1000:floors=3] [--size 96]
                                  [--save-cloud OUT.ply]

* metric-scale error after grounding, |delta * s_true - 1|, median and max over regions, with the
  ``mono-sim`` emulation (unknown per-region scale, holes, noise) on generated houses (target <= 2 %);
* accuracy of the merged cloud against the scene mesh: exact point-to-mesh distance (mean, p95),
  completeness (mesh surface samples -> cloud) and their Chamfer mean; completeness counts every
  mesh face, seen or not (outer wall faces, under furniture), so it is an upper bound;
* ``rgbd`` throughput in frames/s at 256x256 (fusion + voxels + outlier removal, one process, the
  compiled kernels warmed up first; ``--throughput-kernels auto numpy`` adds the array code);
* the same pipeline on the Replica office (frames ray-cast from its scanned mesh along ``traj.txt``),
  when ../shared/data is present.

``--building`` (issue 21, item 6) runs only the pipeline at building scale: discovery and the
recorded tours of one large house, then the rgbd reconstruction, and reports tour frames, wall
seconds of each phase, the reconstruction's peak memory (numpy/Python allocations traced during
the build, and the process's peak RSS), map points and the stored map's size on disk.
``--save-cloud`` writes the map for ``python -m bench.renderer --clouds``.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from shared.geometry import PinholeCamera
from shared.o3d import o3d
from shared.schemas import CameraIntrinsics, Pose

from services.reconstructor.core import (
    RECONSTRUCTORS,
    ReconstructionConfig,
    Reconstructor,
    RegionInput,
    posed_from_matrix,
    region_from_recording,
)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


class MeshRef:
    """Exact distances to a triangle mesh and uniform samples of its surface."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, sample_spacing_m: float = 0.05):
        self.rc = o3d.t.geometry.RaycastingScene()
        m = o3d.t.geometry.TriangleMesh()
        m.vertex.positions = o3d.core.Tensor(vertices.astype(np.float32))
        m.triangle.indices = o3d.core.Tensor(triangles.astype(np.int32))
        self.rc.add_triangles(m)
        legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
        n = int(legacy.get_surface_area() / sample_spacing_m**2)
        self.samples = np.asarray(legacy.sample_points_uniformly(min(n, 2_000_000)).points)

    def score(self, xyz: np.ndarray) -> dict:
        from scipy.spatial import cKDTree

        acc = self.rc.compute_distance(o3d.core.Tensor(xyz.astype(np.float32))).numpy()
        comp, _ = cKDTree(xyz).query(self.samples, workers=-1)
        return {
            "accuracy_mean_m": round(float(acc.mean()), 4), "accuracy_p95_m": round(float(np.percentile(acc, 95)), 4),
            "completeness_mean_m": round(float(comp.mean()), 4),
            "completeness_5cm": round(float((comp < 0.05).mean()), 3),
            "chamfer_mean_m": round(float(0.5 * (acc.mean() + comp.mean())), 4),
            "chamfer_p95_m": round(float(0.5 * (np.percentile(acc, 95) + np.percentile(comp, 95))), 4),
        }


def tour_house(spec: str, size_px: int):
    from services.mapper.core import discover, execute_tours
    from services.robot_io.core.robot import ROBOTS

    cam = CameraIntrinsics(width_px=size_px, height_px=size_px, hfov_deg=90.0)
    robot = ROBOTS.create("sim", {"scene": spec, "camera": cam})
    d = discover(robot)
    recs = execute_tours(robot, d.tours, d.scene, rate_hz=2.0)
    return robot, recs


def run_house(spec: str, size_px: int, seeds: list[int]) -> dict:
    t0 = time.perf_counter()
    robot, recs = tour_house(spec, size_px)
    t_tour = time.perf_counter() - t0
    ref = MeshRef(robot.scene.vertices, robot.scene.triangles)
    out = {"scene": spec, "regions": len(recs), "frames": sum(len(r.frames) for r in recs),
           "tour_s": round(t_tour, 1)}
    with Reconstructor(ReconstructionConfig(backend="rgbd")) as r:
        b = r.build_from_recordings(recs, robot.scene.label_names)
    out["rgbd"] = {"points": len(b.cloud), **ref.score(b.cloud.xyz), "build_s": round(b.timings_s["total"], 2),
                   "delta_mean_rgbd": [round(x.alignment.delta_mean, 4) for x in b.regions]}
    errors, mono_scores, by_region = [], [], {}
    for seed in seeds:
        cfg = ReconstructionConfig(backend="mono-sim", backend_config={"seed": seed})
        with Reconstructor(cfg) as r:
            b = r.build_from_recordings(recs, robot.scene.label_names)
        errors += [x.scale_error for x in b.regions]
        by_region[f"seed{seed}"] = [round(100 * x.scale_error, 2) for x in b.regions]
        mono_scores.append(ref.score(b.cloud.xyz))
    out["mono_sim"] = {
        "regions_x_seeds": len(errors),
        "scale_error_median_pct": round(100 * float(np.median(errors)), 2),
        "scale_error_max_pct": round(100 * float(np.max(errors)), 2),
        "scale_error_pct_by_region": by_region,  # per seed, regions in order
        **{k: round(float(np.mean([s[k] for s in mono_scores])), 4) for k in mono_scores[0]},
    }
    out["_errors"] = errors
    return out


def throughput(spec: str, size_px: int, kernels: tuple[str, ...] = ("auto",)) -> dict:
    """rgbd frames/s (wall) and CPU seconds, full resolution and stride 2; kernels warmed up first
    (a service does it at start), the one-off compile/cache load is reported apart."""
    _, recs = tour_house(spec, size_px)
    regions = [region_from_recording(r) for r in recs]
    rows = {}
    for kernel in kernels:
        for stride in (1, 2):
            backend = RECONSTRUCTORS.create("rgbd", {"pixel_stride": stride, "kernel": kernel})
            warm = backend.warm_up()
            t0, c0 = time.perf_counter(), time.process_time()
            pts = 0
            for reg in regions:
                pts += len(backend.reconstruct(reg).cloud)
            dt, cpu = time.perf_counter() - t0, time.process_time() - c0
            n = sum(len(r.images) for r in regions)
            name = f"stride{stride}" if kernel == "auto" else f"{kernel}_stride{stride}"
            rows[name] = {"kernel": backend.kernel, "frames": n, "seconds": round(dt, 2), "cpu_s": round(cpu, 2),
                          "frames_per_s": round(n / dt, 1), "points": pts, "warm_up_s": round(warm, 2)}
    return {"scene": spec, "size_px": size_px, **rows}


def replica(size_px: int, frames: int, region_frames: int, seeds: list[int]) -> dict | None:
    root = DATA / "replica_office0"
    if not root.is_dir():
        return None
    from services.robot_io.core.render import SceneRenderer
    from libs.world.scene import load_scene

    scene = load_scene(str(root / "office0_mesh.ply"))
    renderer = SceneRenderer(scene)
    poses = np.loadtxt(root / "traj.txt").reshape(-1, 4, 4)
    step = max(1, len(poses) // frames)
    poses = poses[::step][:frames]
    cam = PinholeCamera(size_px, size_px, 90.0)  # Replica: fx = W/2, a 90 deg HFOV
    t0 = time.perf_counter()
    images = []
    for k in range(0, len(poses), 64):
        out = renderer.render(poses[k : k + 64], cam, with_semantic=False)
        images += [posed_from_matrix(out.rgb[i], poses[k + i], cam, out.depth_m[i], index=k + i) for i in range(len(out.rgb))]
    t_render = time.perf_counter() - t0
    h = 1.25
    regions = []
    for rid, k in enumerate(range(0, len(images), region_frames)):
        chunk = images[k : k + region_frames]
        first = chunk[0]
        start = Pose(position_m=tuple(first.position_m - [0.0, 0.0, h]), heading_rad=first.heading_rad)
        regions.append(RegionInput(rid, start, chunk, camera_height_m=h))
    ref = MeshRef(scene.vertices, scene.triangles, 0.02)
    res = {"frames": len(images), "regions": len(regions), "render_s": round(t_render, 1)}
    with Reconstructor(ReconstructionConfig(backend="rgbd")) as r:
        t0 = time.perf_counter()
        b = r.build(regions)
        res["rgbd"] = {"points": len(b.cloud), **ref.score(b.cloud.xyz),
                       "frames_per_s": round(len(images) / (time.perf_counter() - t0), 1)}
    errors = []
    for seed in seeds:
        with Reconstructor(ReconstructionConfig(backend="mono-sim", backend_config={"seed": seed})) as r:
            b = r.build(regions)
        errors += [x.scale_error for x in b.regions]
        res.setdefault("mono_sim_scores", []).append(ref.score(b.cloud.xyz))
    scores = res.pop("mono_sim_scores")
    res["mono_sim"] = {"scale_error_median_pct": round(100 * float(np.median(errors)), 2),
                       "scale_error_max_pct": round(100 * float(np.max(errors)), 2),
                       **{k: round(float(np.mean([s[k] for s in scores])), 4)
                          for k in ("accuracy_mean_m", "accuracy_p95_m", "chamfer_mean_m")}}
    return res


def building(spec: str, size_px: int, save_cloud: str | None = None) -> dict:
    """Item 6 of issue 21: the pipeline after discovery, on one large multi-floor house."""
    import resource
    import tempfile
    import tracemalloc

    from services.mapper.core import discover, execute_tours
    from services.reconstructor.core.store import MapStore
    from services.robot_io.core.robot import ROBOTS

    cam = CameraIntrinsics(width_px=size_px, height_px=size_px, hfov_deg=90.0)
    t0 = time.perf_counter()
    robot = ROBOTS.create("sim", {"scene": spec, "camera": cam})
    t1 = time.perf_counter()
    d = discover(robot)
    t2 = time.perf_counter()
    recs = execute_tours(robot, d.tours, d.scene, rate_hz=2.0)
    t3 = time.perf_counter()
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    tracemalloc.start()
    with Reconstructor(ReconstructionConfig(backend="rgbd")) as r:
        b = r.build_from_recordings(recs, robot.scene.label_names)
    traced_peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    t4 = time.perf_counter()
    rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    with tempfile.TemporaryDirectory() as tmp:
        store = MapStore(tmp, fsync=False)
        t5 = time.perf_counter()
        store.save("building", b.cloud, source=spec, regions=len(b.regions))
        save_s = time.perf_counter() - t5
        store_bytes = sum(f.stat().st_size for f in Path(tmp).rglob("*") if f.is_file())
    if save_cloud:
        b.cloud.save(save_cloud)
    frames = [len(rec.frames) for rec in recs]
    return {
        "scene": spec, "size_px": size_px, "scene_floors": robot.scene.floors,
        "reachable_area_m2": round(robot.nav.reachable_area_m2, 1),
        "explore": d.result.summary(), "floors_mapped": len(d.scene.floors), "regions": len(d.tours),
        "hubs": sum(len(pt.tour.hubs_m) for pt in d.tours), "tours_recorded": len(recs),
        "tour_frames": sum(frames), "max_frames_per_region": max(frames, default=0),
        "seconds": {"sim_load": round(t1 - t0, 1), **{k: round(v, 1) for k, v in d.timings_s.items()},
                    "tours": round(t3 - t2, 1), "reconstruct": round(t4 - t3, 1), "store": round(save_s, 2)},
        "reconstruct_timings_s": {k: round(v, 2) for k, v in b.timings_s.items()},
        "reconstruct_traced_peak_mib": round(traced_peak, 1),
        "process_peak_rss_mib": {"before_reconstruct": round(rss_before, 1), "after": round(rss_after, 1)},
        "map_points": len(b.cloud), "map_store_bytes": store_bytes,
        "map_store_mib": round(store_bytes / 2**20, 1),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--houses", nargs="+", default=["generated:3:area=50", "generated:4:area=50", "generated:1:area=60"])
    ap.add_argument("--size", type=int, default=96, help="camera size of the toured frames (px)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="mono-sim seeds per house")
    ap.add_argument("--throughput-scene", default="generated:3:area=50")
    ap.add_argument("--throughput-size", type=int, default=256)
    ap.add_argument("--throughput-kernels", nargs="+", default=["auto"], choices=["auto", "numba", "numpy"],
                    help="fusion kernels to time (numpy: the array code, for a before/after)")
    ap.add_argument("--no-throughput", action="store_true", help="grounding and accuracy only")
    ap.add_argument("--replica-frames", type=int, default=1000)
    ap.add_argument("--no-replica", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--building", nargs="?", const="generated:0:area=1000:floors=3", default=None,
                    help="only the building-scale run (issue 21, item 6) on this house")
    ap.add_argument("--save-cloud", default=None, help="--building: write the map here (.ply)")
    args = ap.parse_args(argv if argv is not None else [])
    logging.basicConfig(level=logging.WARNING)
    if args.building:
        row = building(args.building, args.size, args.save_cloud)
        print(json.dumps(row), flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(row, indent=2))
        return
    report: dict = {"houses": []}
    all_errors = []
    for spec in args.houses:
        try:
            row = run_house(spec, args.size, args.seeds)
        except Exception as exc:  # a mapper failure on one house must not hide the others
            print(json.dumps({"scene": spec, "error": f"{type(exc).__name__}: {exc}"}), flush=True)
            continue
        all_errors += row.pop("_errors")
        report["houses"].append(row)
        print(json.dumps(row), flush=True)
    if all_errors:
        report["grounding"] = {
            "regions": len(all_errors),
            "scale_error_median_pct": round(100 * float(np.median(all_errors)), 2),
            "scale_error_max_pct": round(100 * float(np.max(all_errors)), 2),
            "target_median_pct": 2.0,
        }
        print(json.dumps({"grounding_all_houses": report["grounding"]}), flush=True)
    if not args.no_throughput:
        report["throughput"] = throughput(args.throughput_scene, args.throughput_size, tuple(args.throughput_kernels))
        print(json.dumps({"rgbd_throughput": report["throughput"], "target_frames_per_s": 200}), flush=True)
    if not args.no_replica:
        rep = replica(args.throughput_size, args.replica_frames, 250, args.seeds)
        report["replica"] = rep
        print(json.dumps({"replica_office0": rep if rep is not None else "skipped (no ../shared/data)"}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
