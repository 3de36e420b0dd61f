"""The oracle policy (evaluation only): follows the reference path with ground-truth geodesics.

It proves the rest of the system sound: if waypoints, motion, the mission loop and the metrics are right,
the oracle succeeds on nearly every episode. It needs ``ctx.oracle`` (goal, reference path, geodesic).
"""

from __future__ import annotations

import math

import numpy as np

from shared.registry import BackendConfig
from shared.schemas import CandidateKind, Decision

from .context import StepContext
from .errors import ContextError
from .policy import POLICIES, Policy


class OracleConfig(BackendConfig):
    """Thresholds of the oracle policy."""

    stop_radius_m: float = 1.5  # stop when this close (geodesic) and no move gets closer by min_gain_m
    min_gain_m: float = 0.3
    reference_weight: float = 0.5  # cost per metre of lateral deviation from the reference path
    lookahead_m: float = 3.0  # aim at the reference point this far ahead of the agent's progress
    allow_euclidean: bool = False  # use straight-line distances when the context has no geodesic
    success_radius_m: float = 3.0  # VLN-CE success: stopping within this geodesic distance
    safety_margin_m: float = 0.5  # never trust a stop closer to the success radius than this
    tabu_radius_m: float = 0.6  # a move ending this near an earlier position revisits it
    tabu_penalty_m: float = 2.0  # added cost per earlier visit near a candidate's end point
    # Where a move ends in height: a candidate is (dx, dy) only, so on stairs its floor point is not at the
    # agent's height. Heights within max_slope * distance (+ margin) are tried, every z_step_m.
    max_slope: float = 0.8  # rise per metre of the steepest walkable ramp or stair (generated: 0.19 / 0.27)
    z_margin_m: float = 0.3
    z_step_m: float = 0.25  # at most twice the geodesic's height tolerance, so no walkable floor is skipped
    snap_tolerance_m: float = 0.15  # a point this near (in plan) to the walkable surface is on it


def point_to_polyline(points: np.ndarray, polyline: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each point to a polyline and the arc length of its nearest point, vectorised.

    Returns (distance (N,), arc length (N,)).
    """
    pts = np.asarray(points, dtype=np.float64)
    line = np.asarray(polyline, dtype=np.float64)
    if len(line) == 1:
        return np.linalg.norm(pts - line[0], axis=1), np.zeros(len(pts))
    a, b = line[:-1], line[1:]
    ab = b - a
    seg_len = np.linalg.norm(ab, axis=1)
    denom = np.maximum(seg_len**2, 1e-12)
    t = np.clip(np.einsum("psd,sd->ps", pts[:, None, :] - a[None], ab) / denom, 0.0, 1.0)
    proj = a[None] + t[..., None] * ab[None]
    d = np.linalg.norm(pts[:, None, :] - proj, axis=2)
    j = np.argmin(d, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    rows = np.arange(len(pts))
    return d[rows, j], cum[j] + t[rows, j] * seg_len[j]


def end_heights(here_m: np.ndarray, targets_xy_m: np.ndarray, geo, config: OracleConfig) -> np.ndarray:
    """The floor height each straight move from ``here_m`` to ``targets_xy_m`` (M, 2) most likely ends at.

    A candidate carries no height; on stairs its floor point lies above or below the agent, and a geodesic
    query at the agent's height snaps to whatever walkable point is nearest in 3-D (a lower tread, the
    floor under a landing), which made the move up the stairs look like a detour and sent the oracle
    down and up the flight until its budget ran out. A height is *on the floor* when the geodesic from
    the point to itself is ~0 (a snapped point pays its snap offset twice). The agent's own height is
    kept when it is on the floor; otherwise heights within reach of the slope are tried and, among
    those on the floor, the one reachable most directly from ``here_m`` wins (ties: the smallest change
    of height). Where none is on the floor (a target inside furniture) the agent's height is kept.
    """
    here = np.asarray(here_m, dtype=np.float64)
    xy = np.asarray(targets_xy_m, dtype=np.float64).reshape(-1, 2)
    r = np.linalg.norm(xy - here[:2], axis=1)
    z = np.full(len(xy), here[2])

    def on_floor(p: np.ndarray) -> bool:
        return geo(p, p) <= 2.0 * config.snap_tolerance_m

    for i in range(len(xy)):
        if on_floor(np.array([xy[i, 0], xy[i, 1], here[2]])):
            continue
        n = int(math.ceil((config.max_slope * r[i] + config.z_margin_m) / config.z_step_m))
        dz = config.z_step_m * np.arange(-n, n + 1)
        dz = dz[np.argsort(np.abs(dz), kind="stable")]
        pts = np.column_stack([np.full((len(dz), 2), xy[i]), here[2] + dz])
        # The walk back is cheap (one shortest-path field from here, cached); the on-floor test costs a
        # field per point, so it runs in order of the walk back and stops at the first success.
        back = np.array([geo(p, here) for p in pts])
        seen: set[float] = set()
        for k in np.argsort(back, kind="stable"):
            if not np.isfinite(back[k]) or round(float(back[k]), 6) in seen:
                continue  # the same snapped point as a height already rejected
            seen.add(round(float(back[k]), 6))
            if on_floor(pts[k]):
                z[i] = pts[k, 2]
                break
    return z


def point_at_arc_length(polyline: np.ndarray, s_m: float) -> np.ndarray:
    """The point of a polyline at arc length ``s_m`` (clamped to its ends)."""
    line = np.asarray(polyline, dtype=np.float64)
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = float(np.clip(s_m, 0.0, cum[-1]))
    j = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    t = 0.0 if seg[j] <= 0 else (s - cum[j]) / seg[j]
    return line[j] + t * (line[j + 1] - line[j])


@POLICIES.register("oracle", OracleConfig)
class OraclePolicy(Policy):
    name = "oracle"

    def __init__(self, config: OracleConfig):
        super().__init__()
        self.config = config
        self._progress_m = 0.0

    def reset(self, mission_id: str) -> None:
        super().reset(mission_id)
        self._progress_m = 0.0

    def _geo(self, ctx: StepContext):
        info = ctx.oracle
        if info is None:
            raise ContextError("the oracle policy needs ctx.oracle (goal, reference path, geodesic)")
        if info.geodesic is not None:
            def geo(a, b):
                d = info.geodesic(a, b)
                return math.inf if d is None else float(d)
            return geo
        if not self.config.allow_euclidean:
            raise ContextError("ctx.oracle has no geodesic callable and allow_euclidean is off")
        return lambda a, b: float(np.linalg.norm(np.asarray(a) - np.asarray(b)))

    def decide(self, ctx: StepContext) -> Decision:
        geo = self._geo(ctx)
        goal = np.asarray(ctx.oracle.goal_m, dtype=np.float64)
        here = ctx.pose.xyz
        d_here = geo(here, goal)
        movable = [v for v in ctx.candidates if v.kind != CandidateKind.STOP]
        stop = ctx.stop_candidate
        if not movable:
            if stop is None:
                raise ContextError("no candidate at all")
            return self._decision(ctx, stop.index, f"no move possible; {d_here:.2f} m from the goal")

        targets = np.stack([ctx.target_m(v) for v in movable])
        targets[:, 2] = end_heights(here, targets[:, :2], geo, self.config)
        d_goal = np.array([geo(t, goal) for t in targets])
        cost = d_goal.copy()
        ref = ctx.oracle.reference_path_m
        if ref is not None and len(ref) > 1:
            ref = np.asarray(ref, dtype=np.float64)
            _, s_here = point_to_polyline(here[None], ref)
            # Progress never goes back: a path that loops near itself must not pull the agent backwards.
            self._progress_m = max(self._progress_m, float(s_here[0]))
            aim = point_at_arc_length(ref, self._progress_m + self.config.lookahead_m)
            lateral, _ = point_to_polyline(targets, ref)
            cost = np.array([geo(t, aim) for t in targets]) + self.config.reference_weight * lateral
        # Tabu: a move back to where the agent already stood is what makes an oracle oscillate
        # (forward, backtrack, forward...). Each earlier visit near the end point costs tabu_penalty_m.
        past = np.asarray(ctx.trajectory_m, dtype=np.float64)[:-1, :2] if len(ctx.trajectory_m) > 1 else None
        if past is not None and len(past):
            near = np.linalg.norm(targets[:, None, :2] - past[None], axis=2) < self.config.tabu_radius_m
            cost = cost + self.config.tabu_penalty_m * near.sum(axis=1)
        best = int(np.argmin(cost))
        gain = d_here - d_goal[best]
        safe = self.config.success_radius_m - self.config.safety_margin_m
        if stop is not None:
            if d_here <= self.config.stop_radius_m and gain < self.config.min_gain_m:
                return self._decision(ctx, stop.index, f"at the goal ({d_here:.2f} m)")
            if d_here <= safe and gain < self.config.min_gain_m:
                return self._decision(ctx, stop.index,
                                      f"within the success radius ({d_here:.2f} m); no move gets closer")
            # The last step of the budget: a stop inside the radius beats a move that cannot be scored.
            if d_here <= safe and ctx.max_steps and ctx.step >= ctx.max_steps - 1:
                return self._decision(ctx, stop.index, f"step budget ending; {d_here:.2f} m from the goal")
        v = movable[best]
        return self._decision(
            ctx, v.index, f"{d_goal[best]:.2f} m from the goal after this move (now {d_here:.2f} m)"
        )
