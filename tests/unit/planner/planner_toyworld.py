"""A tiny labelled 2-D world for closed-loop planner tests (no simulator, no renderer needed).

Landmarks are labelled discs seen as image blocks whose size shrinks with distance; rooms are boxes
whose label covers the lower image rows (the floor just ahead). Enough for policies that read labels,
depth, turns and progress, and fast: a 32x32 view costs microseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from services.planner.core import (
    Ablation,
    HistoryRecorder,
    OracleInfo,
    StepContext,
    action_for,
    build_candidate_views,
    with_stop_and_backtrack,
)
from shared.geometry import panorama_headings, wrap_angle
from shared.schemas import Candidate, CameraIntrinsics, CandidateKind, Panorama, Pose, RenderResult

PX = 32


@dataclass
class ToyWorld:
    landmarks: dict[str, tuple[float, float]]  # name -> (x, y)
    rooms: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)  # name -> x0,y0,x1,y1
    bounds: tuple[float, float, float, float] = (-2.0, -2.0, 10.0, 10.0)
    with_labels: bool = True

    def __post_init__(self):
        names = list(self.landmarks) + [f"{r} floor" for r in self.rooms] + ["wall"]
        self.label_names = {i: n for i, n in enumerate(names)}
        self._id = {n: i for i, n in self.label_names.items()}

    def room_at(self, x, y):
        for r, (x0, y0, x1, y1) in self.rooms.items():
            if x0 <= x <= x1 and y0 <= y <= y1:
                return r
        return None

    def view(self, pos, heading, hfov_deg=90.0):
        rgb = np.full((PX, PX, 3), 90, np.uint8)
        labels = np.full((PX, PX), self._id["wall"], np.int32)
        depth = np.full((PX, PX), 4.0, np.float32)
        half = math.radians(hfov_deg) / 2
        ahead = (pos[0] + 1.0 * math.cos(heading), pos[1] + 1.0 * math.sin(heading))
        room = self.room_at(*ahead)
        if room is not None:
            labels[PX * 3 // 4 :, :] = self._id[f"{room} floor"]
            depth[PX * 3 // 4 :, :] = 1.0
        for name, (lx, ly) in self.landmarks.items():
            d = math.hypot(lx - pos[0], ly - pos[1])
            b = float(wrap_angle(math.atan2(ly - pos[1], lx - pos[0]) - heading))
            if abs(b) >= half or d > 9.0:
                continue
            u = PX / 2 - math.tan(b) / math.tan(half) * PX / 2
            w = int(np.clip(PX * 0.6 / max(d, 0.3), 1, PX))
            u0, u1 = int(max(0, u - w / 2)), int(min(PX, u + w / 2 + 1))
            v0 = max(0, PX // 2 - w // 2)
            labels[v0 : v0 + w, u0:u1] = self._id[name]
            depth[v0 : v0 + w, u0:u1] = d
            rgb[v0 : v0 + w, u0:u1] = (200, 30 + 10 * self._id[name], 30)
        return rgb, (labels if self.with_labels else None), depth

    def inside(self, x, y):
        x0, y0, x1, y1 = self.bounds
        return x0 <= x <= x1 and y0 <= y <= y1


def waypoints(world: ToyWorld, pose: Pose, step_m=1.5) -> list[Candidate]:
    out = []
    for k in range(12):
        rel = float(wrap_angle(k * math.pi / 6))
        h = pose.heading_rad + rel
        dx, dy = step_m * math.cos(h), step_m * math.sin(h)
        if world.inside(pose.position_m[0] + dx, pose.position_m[1] + dy):
            out.append(Candidate(index=len(out), dx_m=dx, dy_m=dy, angle_rad=rel, distance_m=step_m))
    return out


def run_episode(world, policy, instruction, start=(0.0, 0.0, 0.0), heading=0.0, max_steps=30,
                goal=None, ablation=Ablation(), geodesic=None, reference=None):
    """Closed loop: observe -> candidates -> anticipated views -> decide -> act.

    Returns (trajectory, stopped, decisions)."""
    pose = Pose(position_m=start, heading_rad=heading)
    traj = [np.array(start, float)]
    history = HistoryRecorder()
    prev = None
    decisions = []
    policy.reset("toy")
    for step in range(max_steps):
        heads = panorama_headings(pose.heading_rad)
        views = [world.view(pose.position_m, h) for h in heads]
        pano = Panorama(
            pose=pose, camera=CameraIntrinsics(width_px=PX, height_px=PX), headings_rad=heads,
            rgb=np.stack([v[0] for v in views]), depth_m=np.stack([v[2] for v in views]),
            semantic=np.stack([v[1] for v in views]) if world.with_labels else None,
        )
        cands = with_stop_and_backtrack(waypoints(world, pose), pose, prev)
        movable = [c for c in cands if c.kind != CandidateKind.STOP]
        rendered = [
            world.view((pose.position_m[0] + c.dx_m, pose.position_m[1] + c.dy_m), math.atan2(c.dy_m, c.dx_m),
                       ablation.anticipation_hfov_deg)
            for c in movable
        ]
        render = RenderResult(
            map_id="toy", version=1, rgb=np.stack([r[0] for r in rendered]), depth_m=np.stack([r[2] for r in rendered]),
            hole_mask=np.zeros((len(rendered), PX, PX), bool),
            labels=np.stack([r[1] for r in rendered]) if world.with_labels else None,
        ) if ablation.anticipation else None
        ctx = StepContext(
            instruction=instruction, step=step, pose=pose, candidates=build_candidate_views(cands, pano, render),
            trajectory_m=np.array(traj), history=history.compressed(), label_names=world.label_names,
            ablation=ablation, mission_id="toy", max_steps=max_steps, panorama=pano,
            oracle=OracleInfo(goal_m=np.asarray(goal, float), reference_path_m=reference, geodesic=geodesic)
            if goal is not None else None,
        )
        d = policy.decide(ctx)
        decisions.append(d)
        chosen = ctx.candidate(d.candidate_index)
        if chosen.kind == CandidateKind.STOP:
            return np.array(traj), True, decisions
        history.record(step, pano.rgb[0], action_for(chosen.candidate))
        prev = pose.position_m
        c = chosen.candidate
        pose = Pose(position_m=(pose.position_m[0] + c.dx_m, pose.position_m[1] + c.dy_m, 0.0),
                    heading_rad=math.atan2(c.dy_m, c.dx_m))
        traj.append(pose.xyz)
    return np.array(traj), False, decisions
