"""Write a picture of a stored map (top-down spatial map + an oblique splat view), or build one first.

    # explore, tour, reconstruct and store a generated house, then draw it:
    python -m tools.map_pictures --build generated:3:area=50 --root runs/maps \\
        --map-id house3 --backend mono-sim --out runs/house3.png
    # draw an existing map:
    python -m tools.map_pictures --root runs/maps --map-id house3 --out map.png
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import cv2
import numpy as np

from services.reconstructor.core import MapStore, ReconstructionConfig, Reconstructor
from services.renderer.core import SpatialMapper
from shared.geometry import PinholeCamera
from libs.pointrender import RENDERERS, IndexedCloud
from shared.schemas import CameraIntrinsics, Pose


def build(spec: str, store: MapStore, map_id: str, backend: str, size_px: int) -> None:
    from services.mapper.core import discover, execute_tours
    from services.robot_io.core.robot import ROBOTS

    robot = ROBOTS.create("sim", {"scene": spec, "camera": CameraIntrinsics(width_px=size_px, height_px=size_px)})
    d = discover(robot)
    recs = execute_tours(robot, d.tours, d.scene, rate_hz=2.0)
    with Reconstructor(ReconstructionConfig(backend=backend)) as r:
        b = r.build_from_recordings(recs, robot.scene.label_names)
    info = store.save(map_id, b.cloud, source=spec, regions=len(b.regions), scale_factors=b.scale_factors,
                      timings_s=b.timings_s, details=b.details())
    print(json.dumps({"map_id": info.map_id, "version": info.version, "points": info.point_count,
                      "scale_errors": [r.scale_error for r in b.regions]}))


def draw(store: MapStore, map_id: str, out: Path, size_px: int = 768) -> None:
    m = store.load(map_id)
    index = IndexedCloud(m.cloud)
    lo, hi = m.cloud.bounds()
    floor_z = float(np.percentile(m.cloud.xyz[:, 2], 2))
    centre = (lo + hi) / 2.0
    top = SpatialMapper().draw(index, Pose(position_m=(float(centre[0]), float(centre[1]), floor_z)), size_px=size_px)
    # An oblique bird's-eye splat from outside a corner of the map, looking at its centre.
    eye = np.array([lo[0] - 1.0, lo[1] - 1.0, floor_z + max(hi[0] - lo[0], hi[1] - lo[1]) * 0.8])
    fwd = centre - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    wfc = np.eye(4)
    wfc[:3, :3] = np.stack([right, np.cross(fwd, right), fwd], axis=1)
    wfc[:3, 3] = eye
    view = RENDERERS.create("numpy", {"far_m": 100.0, "lod_points_per_px": None}).render_poses(
        index, [wfc], PinholeCamera(size_px, size_px, 70.0), with_labels=False)
    img = np.concatenate([top.image[:, :, :3], view.rgb[0]], axis=1) if top.image.shape[0] == size_px else view.rgb[0]
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR))
    print(f"wrote {out} ({m.info.point_count} points, map {map_id} v{m.info.version})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path("runs/maps"))
    ap.add_argument("--map-id", required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--build", metavar="SCENE", default=None, help="explore + reconstruct this scene first")
    ap.add_argument("--backend", default="rgbd", help="regional reconstruction backend (rgbd, mono-sim)")
    ap.add_argument("--camera-px", type=int, default=96)
    ap.add_argument("--size", type=int, default=768)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    store = MapStore(args.root)
    if args.build:
        build(args.build, store, args.map_id, args.backend, args.camera_px)
    draw(store, args.map_id, args.out, args.size)


if __name__ == "__main__":
    main()
