"""The VLN-CE oracle: discrete shortest-path actions (Habitat's ShortestPathFollower) -> ground truth."""

from __future__ import annotations

import math

import numpy as np

from shared.geometry import wrap_angle
from shared.schemas import Pose

from ..errors import EpisodeGenerationError
from ..navgrid import NavGrid
from .format import MOVE_FORWARD, STOP, TURN_LEFT, TURN_RIGHT, EpisodeDataset, GroundTruth


def follow_path(
    nav: NavGrid,
    start: Pose,
    goal_m,
    step_m: float = 0.25,
    turn_deg: float = 15.0,
    stop_radius_m: float = 0.5,
) -> GroundTruth:
    """The VLN-CE oracle: discrete actions along the shortest path until within ``stop_radius_m``.

    Like Habitat's ``ShortestPathFollower``: turn (15 deg) towards the next corner of the path
    until the heading is within half a turn of it, else step forward 0.25 m; stop near the goal.
    Forward steps that hit an obstacle end where the agent stops, as in the simulator.
    """
    goal = np.asarray(goal_m, dtype=np.float64)
    path = nav.shortest_path(start.xyz, goal)
    if path is None:
        raise EpisodeGenerationError(f"no walkable path from {start.position_m} to {tuple(goal)}")
    turn = math.radians(turn_deg)
    pos = np.array(path[0], dtype=np.float64)
    pos[:2] = start.xyz[:2]
    heading = float(start.heading_rad)
    locations, actions = [pos.copy()], []
    budget = int(4 * (np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)) / step_m + 2 * math.pi / turn)) + 50
    stuck = False
    while len(actions) < budget:
        if np.hypot(*(goal[:2] - pos[:2])) <= stop_radius_m and abs(goal[2] - pos[2]) < 0.5:
            break
        # Re-plan from where the agent is (the goal's distance field is cached): quantised turns
        # drift off the line, and the next corner is what to face.
        route = nav.shortest_path(pos, goal)
        if route is None:
            raise EpisodeGenerationError(f"the oracle left the walkable region at {tuple(pos)}")
        k = 1
        while k < len(route) - 1 and np.hypot(*(route[k][:2] - pos[:2])) < 0.5 * step_m:
            k += 1
        d = route[min(k, len(route) - 1)][:2] - pos[:2]
        err = float(wrap_angle(math.atan2(d[1], d[0]) - heading))
        if stuck:
            # Pinned against a door jamb or a corner: take the quantised heading whose step gains
            # the most geodesic distance (Habitat's greedy geodesic follower), then walk.
            here = nav.geodesic_distance(pos, goal)
            best_j, best_gain = 0, 1e-3
            n_dirs = int(round(2 * math.pi / turn))
            for j in range(-(n_dirs // 2) + 1, n_dirs // 2 + 1):
                h = heading + j * turn
                e = _slide_step(nav, pos, step_m * np.array([math.cos(h), math.sin(h)]))
                gain = here - nav.geodesic_distance(e, goal)
                if gain > best_gain + 1e-9 or (abs(gain - best_gain) <= 1e-9 and abs(j) < abs(best_j)):
                    best_j, best_gain = j, gain
            if best_gain <= 1e-3:
                raise EpisodeGenerationError(f"the oracle is stuck at {tuple(np.round(pos, 3))}")
            actions += [TURN_LEFT if best_j > 0 else TURN_RIGHT] * abs(best_j)
            heading = float(wrap_angle(heading + best_j * turn))
        elif abs(err) > turn / 2 + 1e-9:
            actions.append(TURN_LEFT if err > 0 else TURN_RIGHT)
            heading = float(wrap_angle(heading + (turn if err > 0 else -turn)))
            continue
        end = _slide_step(nav, pos, step_m * np.array([math.cos(heading), math.sin(heading)]))
        actions.append(MOVE_FORWARD)
        stuck = float(np.hypot(*(end[:2] - pos[:2]))) < 0.01
        pos = end
        locations.append(pos.copy())
    else:
        raise EpisodeGenerationError(f"oracle did not reach the goal within {budget} actions")
    actions.append(STOP)
    return GroundTruth.from_world(np.array(locations), actions)


def _slide_step(nav: NavGrid, pos: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """One forward step with the simulator's collision model: full, slid along an axis, or partial."""
    end, ok = nav.walk(pos, np.array([pos[0] + delta[0], pos[1] + delta[1], pos[2]]))
    if ok:
        return end
    best, best_gain = end, float(np.dot(end[:2] - pos[:2], delta))
    for axis in (0, 1):
        if abs(delta[axis]) < 1e-6:
            continue
        g = pos.copy()
        g[axis] += delta[axis]
        e, _ = nav.walk(pos, g)
        gain = float(np.dot(e[:2] - pos[:2], delta))
        if gain > best_gain:
            best, best_gain = e, gain
    return best


def ground_truth_for(dataset: EpisodeDataset, nav: NavGrid, **follow_kw) -> dict[str, GroundTruth]:
    """Ground-truth records for every episode of ``dataset`` (in its scene's ``nav``), keyed by id."""
    return {str(e.episode_id): follow_path(nav, e.start_pose, e.goal_m, **follow_kw) for e in dataset.episodes}
