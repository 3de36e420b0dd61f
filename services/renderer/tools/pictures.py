"""Write pictures of the renderer's output: a candidate's anticipated view beside the ray-cast
ground-truth view, and a spatial map.

    python -m services.renderer.tools.pictures --out /tmp/renderer-pictures

Uses the Replica office (a cloud sampled from its mesh) when ../shared/data is present, otherwise
the built two-room flat (which also has room labels for the map).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from services.renderer.core import RENDERERS, IndexedCloud, SpatialMapper
from services.renderer.tools import scenes
from shared.geometry import PinholeCamera, camera_pose
from shared.schemas import Candidate, Pose, ViewPose

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = np.concatenate([np.full((22, img.shape[1], 3), 255, np.uint8), img], axis=0)
    cv2.putText(out, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--scene", choices=["auto", "room", "replica"], default="auto")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    use_replica = args.scene == "replica" or (args.scene == "auto" and DATA.is_dir())
    if use_replica:
        mesh = scenes.replica_office(DATA)
        wfc = scenes.replica_view_poses(DATA, 1, stride=1)[0]
        # The agent stands under the recorded camera, facing its view direction.
        fwd = wfc[:3, 2]
        agent = wfc[:3, 3] - np.array([0.0, 0.0, 1.25])
        heading = math.atan2(fwd[1], fwd[0])
        floor_z = float(mesh.vertices[:, 2].min())
        name = "replica_office0"
    else:
        mesh = scenes.built_room()
        agent, heading, floor_z, name = np.array([1.5, 3.0, 0.0]), 0.0, 0.0, "built_room"
    cloud = scenes.sample_mesh(mesh, args.points)
    index = IndexedCloud(cloud)
    cam = PinholeCamera(256, 256, 90.0)

    # Candidates fanned out ahead of the agent, 1.5-2.5 m away.
    cands = []
    for i, (ang, dist) in enumerate([(0.6, 1.8), (0.0, 2.2), (-0.7, 1.6)]):
        a = heading + ang
        cands.append(Candidate(index=i, dx_m=dist * math.cos(a), dy_m=dist * math.sin(a),
                               angle_rad=ang, distance_m=dist))
    views = [ViewPose(position_m=(agent[0] + c.dx_m, agent[1] + c.dy_m, agent[2]),
                      heading_rad=math.atan2(c.dy_m, c.dx_m)) for c in cands]
    renderer = RENDERERS.create("numpy")
    out = renderer.render(index, views, cam)
    gt = scenes.RaycastCamera(mesh)
    rows = []
    for i, v in enumerate(views):
        g, _, _ = gt.render(camera_pose(v.position_m, v.heading_rad, v.pitch_rad), cam)
        holes = np.where(out.hole_mask[i][..., None], np.array([255, 0, 255], np.uint8), out.rgb[i])
        rows.append(np.concatenate([
            _label(out.rgb[i], f"candidate {i}: anticipated"),
            _label(holes, "holes in magenta"),
            _label(g, "ground truth (ray cast)"),
        ], axis=1))
    sheet = np.concatenate(rows, axis=0)
    cv2.imwrite(str(args.out / f"{name}_anticipated_vs_gt.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))

    pose = Pose(position_m=(float(agent[0]), float(agent[1]), floor_z), heading_rad=heading)
    back = -1.2 * np.array([math.cos(heading), math.sin(heading)])
    traj = np.array([[agent[0] + back[0] * t, agent[1] + back[1] * t + 0.3 * math.sin(2 * t), floor_z]
                     for t in np.linspace(1.0, 0.0, 6)])
    mapper = SpatialMapper()
    for agent_up in (False, True):
        m = mapper.draw(index, pose, traj, cands, agent_up=agent_up, size_px=512)
        suffix = "agent_up" if agent_up else "absolute"
        cv2.imwrite(str(args.out / f"{name}_spatial_map_{suffix}.png"), cv2.cvtColor(m.image, cv2.COLOR_RGB2BGR))
    print(f"wrote pictures of {name} to {args.out}")


if __name__ == "__main__":
    main()
