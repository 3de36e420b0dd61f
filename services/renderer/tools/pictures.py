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

from services.renderer.core import OccupancyGrid, SpatialMapper
from services.renderer.core.spatial_map import FREE
from services.renderer.tools import scenes
from shared.geometry import PinholeCamera, camera_pose
from libs.pointrender import RENDERERS, IndexedCloud
from shared.schemas import Candidate, Pose, ViewPose

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = np.concatenate([np.full((22, img.shape[1], 3), 255, np.uint8), img], axis=0)
    cv2.putText(out, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return out


# Candidate search for a small furnished room (the Replica office, about 6 x 5 m).
SMALL_ROOM = {"clearance_m": 0.2, "look_ahead_m": 0.6, "distances_m": (1.5, 1.2, 0.9, 0.6)}


def free_space_candidates(
    grid: OccupancyGrid,
    agent_xy: np.ndarray,
    heading_rad: float,
    n: int = 3,
    clearance_m: float = 0.3,
    look_ahead_m: float = 1.0,
    distances_m: tuple[float, ...] = (2.2, 1.8, 1.5, 1.2, 0.9),
) -> list[Candidate]:
    """Up to ``n`` candidate waypoints ahead of the agent (within +-100 deg of its heading), spread
    in angle, that a robot could really reach and whose view is not into a wall: the straight path
    from the agent and ``look_ahead_m`` beyond the waypoint (the direction its view faces) cross
    only FREE cells at least ``clearance_m`` from any obstacle or unknown cell."""
    free = (grid.cells == FREE).astype(np.uint8)
    clear_m = cv2.distanceTransform(free, cv2.DIST_L2, 5) * grid.cell_m

    def clear(xy: np.ndarray) -> bool:
        rc = grid.world_to_cell(xy)
        inside = (rc[:, 0] >= 0) & (rc[:, 0] < free.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < free.shape[1])
        return bool(inside.all()) and bool((clear_m[rc[:, 0], rc[:, 1]] >= clearance_m).all())

    found: list[tuple[float, float]] = []
    for ang in np.radians(np.arange(0.0, 101.0, 10.0)).repeat(2) * np.tile([1.0, -1.0], 11):
        if any(abs(ang - a) < math.radians(35.0) for a, _ in found):
            continue  # keep the candidates spread out, like the waypoint predictor's NMS
        direction = np.array([math.cos(heading_rad + ang), math.sin(heading_rad + ang)])
        for dist in distances_m:
            # From a little ahead of the agent: where it stands may itself hug furniture.
            ray = np.linspace(0.25, dist + look_ahead_m, int((dist + look_ahead_m) / (grid.cell_m / 2)) + 2)
            if clear(agent_xy + ray[:, None] * direction):
                found.append((float(ang), dist))
                break
        if len(found) == n:
            break
    if not found:
        raise RuntimeError("no free-space candidate around the agent: is it inside the map?")
    found.sort()
    return [
        Candidate(index=i, dx_m=d * math.cos(heading_rad + a), dy_m=d * math.sin(heading_rad + a),
                  angle_rad=a, distance_m=d)
        for i, (a, d) in enumerate(found)
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--scene", choices=["auto", "room", "replica"], default="auto")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    use_replica = args.scene == "replica" or (args.scene == "auto" and DATA.is_dir())
    mapper = SpatialMapper()
    if use_replica:
        mesh = scenes.replica_office(DATA)
        floor_z = float(np.percentile(mesh.vertices[:, 2], 1.0))
        index = IndexedCloud(scenes.sample_mesh(mesh, args.points))
        # The office is small and furnished, and a hand-held scan passes over tables: the agent
        # stands under one of the recorded cameras with the most free space around it, facing the
        # direction (of eight) that leaves the most room for candidates.
        grid = mapper.grid(index, floor_z)
        poses = scenes.replica_poses(DATA)
        clear_m = cv2.distanceTransform((grid.cells == FREE).astype(np.uint8), cv2.DIST_L2, 5) * grid.cell_m
        rc = np.clip(grid.world_to_cell(poses[:, :2, 3]), 0, np.array(grid.cells.shape) - 1)
        best: tuple[int, np.ndarray, float] = (0, poses[0, :3, 3], 0.0)
        for i in np.argsort(-clear_m[rc[:, 0], rc[:, 1]], kind="stable")[:20]:
            for h in np.linspace(-math.pi, math.pi, 8, endpoint=False):
                try:
                    found = len(free_space_candidates(grid, poses[i, :2, 3], float(h), **SMALL_ROOM))
                except RuntimeError:
                    continue
                if found > best[0]:
                    best = (found, poses[i, :3, 3], float(h))
        agent = np.array([best[1][0], best[1][1], floor_z])
        heading = best[2]
        cand_args = SMALL_ROOM
        name = "replica_office0"
    else:
        mesh = scenes.built_room()
        agent, heading, floor_z, name = np.array([1.5, 3.0, 0.0]), 0.0, 0.0, "built_room"
        cand_args = {}
        index = IndexedCloud(scenes.sample_mesh(mesh, args.points))
    cam = PinholeCamera(256, 256, 90.0)

    cands = free_space_candidates(mapper.grid(index, floor_z), agent[:2], heading, **cand_args)
    views = [ViewPose(position_m=(agent[0] + c.dx_m, agent[1] + c.dy_m, floor_z),
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
    for agent_up in (False, True):
        m = mapper.draw(index, pose, traj, cands, agent_up=agent_up, size_px=512)
        suffix = "agent_up" if agent_up else "absolute"
        cv2.imwrite(str(args.out / f"{name}_spatial_map_{suffix}.png"), cv2.cvtColor(m.image, cv2.COLOR_RGB2BGR))
    print(f"wrote pictures of {name} to {args.out}")


if __name__ == "__main__":
    main()
