"""Episode generation in labelled scenes: start, goal by an object, reference path, instruction."""

from __future__ import annotations

import math

import numpy as np

from shared.schemas import Pose

from ..errors import EpisodeGenerationError
from ..navgrid import NavGrid
from ..scene import Scene
from .format import Episode, EpisodeDataset
from .instructions import build_vocab, describe_path, tokens_for


def generate_episodes(
    scene: Scene,
    nav: NavGrid,
    count: int,
    seed: int = 0,
    min_geodesic_m: float = 5.0,
    max_geodesic_m: float = 20.0,
    waypoint_spacing_m: float = 2.5,
    goal_radius_m: float = 3.0,
    first_episode_id: int = 1,
) -> EpisodeDataset:
    """R2R-style episodes: a start in one room, a goal next to an object elsewhere, the shortest
    path resampled into reference waypoints, and an instruction from rooms, turns and landmarks."""
    if not scene.objects:
        raise EpisodeGenerationError(f"scene {scene.name!r} has no labelled objects to build instructions from")
    rng = np.random.default_rng(seed)
    episodes: list[Episode] = []
    texts: list[str] = []
    attempts = 0
    while len(episodes) < count:
        attempts += 1
        if attempts > 200 * count:
            raise EpisodeGenerationError(f"only {len(episodes)} of {count} episodes within {min_geodesic_m}-{max_geodesic_m} m")
        obj = scene.objects[int(rng.integers(len(scene.objects)))]
        if obj.label in ("painting", "rug", "chair"):
            continue
        goal = _goal_near(nav, obj, scene.room(obj.room))
        if goal is None:
            continue
        start = nav.sample_navigable(rng)
        if scene.room_at(start) is None or scene.room_at(start).name == obj.room:
            continue
        d = nav.geodesic_distance(start, goal)
        if not (min_geodesic_m <= d <= max_geodesic_m):
            continue
        path = nav.shortest_path(start, goal)
        if path is None:
            continue
        heading = float(rng.uniform(-math.pi, math.pi))
        ref = _waypoints(path, waypoint_spacing_m)
        text = describe_path(scene, path, heading, obj)
        pose = Pose(position_m=tuple(float(v) for v in start), heading_rad=heading)
        episodes.append(Episode.from_world(first_episode_id + len(episodes), scene.source or scene.name, pose, goal, ref, text, d, goal_radius_m=goal_radius_m))
        texts.append(text)
    vocab = build_vocab(texts)
    for e in episodes:
        e.raw["instruction"]["instruction_tokens"] = tokens_for(e.instruction, vocab)
    return EpisodeDataset(episodes, {"instruction_vocab": vocab})


def _goal_near(nav: NavGrid, obj, room) -> np.ndarray | None:
    """The main-component node of the object's room closest to its footprint, within 1 m of it."""
    c = np.array(obj.position_m)
    main = nav.component == nav.main_component
    n = nav.nodes_m
    # Same room only: the nearest cell may otherwise be behind the wall the object stands against.
    in_room = (
        (n[:, 0] > room.min_xy_m[0]) & (n[:, 0] < room.max_xy_m[0]) & (n[:, 1] > room.min_xy_m[1]) & (n[:, 1] < room.max_xy_m[1])
    )
    near = main & in_room & (np.abs(n[:, 2] - c[2]) < 0.3)
    half = np.array(obj.size_m[:2]) / 2
    d = np.maximum(np.abs(nav.nodes_m[:, :2] - c[:2]) - half, 0.0)
    dist = np.hypot(d[:, 0], d[:, 1])
    dist[~near] = np.inf
    i = int(np.argmin(dist))
    return nav.nodes_m[i].copy() if dist[i] <= 1.0 else None


def _waypoints(path: np.ndarray, spacing_m: float) -> np.ndarray:
    """Reference path: the path's corners, with long legs split so gaps stay under ``spacing_m``."""
    out = [path[0]]
    for a, b in zip(path[:-1], path[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing_m)))
        for k in range(1, n + 1):
            out.append(a + (b - a) * k / n)
    return np.array(out)
