"""R2R-CE / RxR-CE episodes: exact reading and writing, and generation in procedural houses.

The file format is VLN-CE's: ``{"episodes": [...], "instruction_vocab": {...}}`` (gzip JSON), each
episode with ``episode_id``, ``trajectory_id``, ``scene_id``, ``start_position`` and
``reference_path`` / goal ``position`` in Habitat coordinates (**y up**), ``start_rotation`` as a
quaternion ``[x, y, z, w]``, ``info.geodesic_distance``, ``goals[{position, radius}]`` and
``instruction{instruction_text, instruction_tokens}`` (RxR-CE adds fields such as ``language``;
they are kept). :class:`Episode` keeps the raw record, so a read-write round trip is exact to the
byte of the JSON text, and exposes world-frame (z-up) views through properties: this module is
the one place where Habitat coordinates are converted.
"""

from __future__ import annotations

import copy
import gzip
import json
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.geometry import habitat_quaternion_to_heading, habitat_to_world, heading_to_habitat_quaternion, world_to_habitat, wrap_angle
from shared.schemas import Pose

from .errors import EpisodeFormatError, EpisodeGenerationError, SceneNotFoundError
from .navgrid import NavGrid
from .scene import Scene, is_generated_spec, resolve_scene_path

log = logging.getLogger(__name__)

_REQUIRED = ("episode_id", "scene_id", "start_position", "start_rotation", "goals")


@dataclass
class Episode:
    """One VLN-CE episode; ``raw`` is the record exactly as in the file (Habitat frame)."""

    raw: dict[str, Any]

    def __post_init__(self) -> None:
        missing = [k for k in _REQUIRED if k not in self.raw]
        if missing:
            raise EpisodeFormatError(f"episode {self.raw.get('episode_id', '?')} lacks {', '.join(missing)}")

    @property
    def episode_id(self):
        return self.raw["episode_id"]

    @property
    def scene_id(self) -> str:
        return self.raw["scene_id"]

    @property
    def instruction(self) -> str:
        return self.raw.get("instruction", {}).get("instruction_text", "")

    @property
    def start_pose(self) -> Pose:
        """The start pose in the world frame (z up)."""
        p = habitat_to_world(self.raw["start_position"])
        return Pose(position_m=tuple(float(v) for v in p), heading_rad=habitat_quaternion_to_heading(self.raw["start_rotation"]))

    @property
    def goal_m(self) -> np.ndarray:
        return habitat_to_world(self.raw["goals"][0]["position"])

    @property
    def goal_radius_m(self) -> float:
        return float(self.raw["goals"][0].get("radius", 3.0))

    @property
    def reference_path_m(self) -> np.ndarray:
        """(P, 3) world-frame reference path (empty if the episode has none)."""
        ref = self.raw.get("reference_path") or []
        return habitat_to_world(np.asarray(ref, dtype=np.float64).reshape(-1, 3))

    @property
    def geodesic_distance_m(self) -> float | None:
        d = self.raw.get("info", {}).get("geodesic_distance")
        return None if d is None else float(d)

    def scene_path(self, scenes_dir: Path | str | None) -> str:
        """The scene spec to load: generated specs as they are, files resolved under ``scenes_dir``.

        Raises :class:`SceneNotFoundError` (naming the file and the directory) when the file is missing.
        """
        if is_generated_spec(self.scene_id):
            return self.scene_id
        try:
            return str(resolve_scene_path(self.scene_id, scenes_dir))
        except SceneNotFoundError as exc:
            raise SceneNotFoundError(exc.path, scenes_dir) from None

    @classmethod
    def from_world(
        cls,
        episode_id: int,
        scene_id: str,
        start: Pose,
        goal_m,
        reference_path_m: np.ndarray,
        instruction: str,
        geodesic_distance_m: float,
        trajectory_id: int | None = None,
        goal_radius_m: float = 3.0,
        tokens: list[int] | None = None,
        extra: dict[str, Any] | None = None,
    ) -> Episode:
        """Build a record from world-frame (z-up) quantities."""
        raw: dict[str, Any] = {
            "episode_id": int(episode_id),
            "trajectory_id": int(episode_id if trajectory_id is None else trajectory_id),
            "scene_id": scene_id,
            "start_position": [float(v) for v in world_to_habitat(start.xyz)],
            "start_rotation": [float(v) for v in heading_to_habitat_quaternion(start.heading_rad)],
            "info": {"geodesic_distance": float(geodesic_distance_m)},
            "goals": [{"position": [float(v) for v in world_to_habitat(np.asarray(goal_m, dtype=float))], "radius": float(goal_radius_m)}],
            "instruction": {"instruction_text": instruction, "instruction_tokens": list(tokens or [])},
            "reference_path": [[float(v) for v in world_to_habitat(p)] for p in np.asarray(reference_path_m, dtype=float)],
        }
        raw.update(extra or {})
        return cls(raw)


@dataclass
class EpisodeDataset:
    """A VLN-CE dataset file: episodes plus whatever else the file holds (vocabulary, ...)."""

    episodes: list[Episode]
    extra: dict[str, Any] = field(default_factory=dict)  # every top-level key except "episodes"
    key_order: list[str] = field(default_factory=lambda: ["episodes", "instruction_vocab"])

    def to_json(self) -> str:
        doc: dict[str, Any] = {}
        for k in self.key_order:
            if k == "episodes":
                doc["episodes"] = [e.raw for e in self.episodes]
            elif k in self.extra:
                doc[k] = self.extra[k]
        for k, v in self.extra.items():
            doc.setdefault(k, v)
        doc.setdefault("episodes", [e.raw for e in self.episodes])
        # json's defaults (", ", ": ", no sorting) are what the VLN-CE files use.
        return json.dumps(doc)

    def by_id(self) -> dict[Any, Episode]:
        return {e.episode_id: e for e in self.episodes}


def read_episodes(path: Path | str) -> EpisodeDataset:
    """Read an R2R-CE / RxR-CE ``.json.gz`` (or plain ``.json``) episode file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"episode file not found: {path}")
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", encoding="utf-8") as f:
        try:
            doc = json.load(f)
        except json.JSONDecodeError as exc:
            raise EpisodeFormatError(f"{path}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("episodes"), list):
        raise EpisodeFormatError(f"{path}: expected an object with an 'episodes' list")
    episodes = [Episode(e) for e in doc["episodes"]]
    extra = {k: v for k, v in doc.items() if k != "episodes"}
    return EpisodeDataset(episodes, extra, list(doc.keys()))


def write_episodes(dataset: EpisodeDataset, path: Path | str) -> Path:
    """Write a dataset; ``.gz`` paths are gzip-compressed (mtime 0, so the bytes are reproducible)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = dataset.to_json().encode("utf-8")
    if path.suffix == ".gz":
        with open(path, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as f:
            f.write(data)
    else:
        path.write_bytes(data)
    return path


# --- generation ------------------------------------------------------------------------------------


def _tokenize(text: str) -> list[str]:
    return re.findall(r"[a-z0-9]+|[.,]", text.lower())


def build_vocab(texts: list[str]) -> dict[str, Any]:
    """An ``instruction_vocab`` in the R2R-CE layout (pad 0, unk 1, then sorted words)."""
    words = ["<pad>", "<unk>"] + sorted({w for t in texts for w in _tokenize(t)})
    idx = {w: i for i, w in enumerate(words)}
    return {"word_list": words, "word2idx_dict": idx, "stoi": dict(idx), "itos": list(words), "num_vocab": len(words), "UNK_INDEX": 1, "PAD_INDEX": 0}


def tokens_for(text: str, vocab: dict[str, Any], length: int = 200) -> list[int]:
    idx = vocab["word2idx_dict"]
    toks = [idx.get(w, vocab["UNK_INDEX"]) for w in _tokenize(text)][:length]
    return toks + [vocab["PAD_INDEX"]] * (length - len(toks))


def _turn_word(angle: float) -> str | None:
    a = math.degrees(float(wrap_angle(angle)))
    if abs(a) < 35:
        return None
    if abs(a) > 135:
        return "turn around"
    if abs(a) > 60:
        return "turn left" if a > 0 else "turn right"
    return "bear left" if a > 0 else "bear right"


def describe_path(scene: Scene, path_m: np.ndarray, start_heading_rad: float, goal_object=None) -> str:
    """An R2R-style instruction from the path's rooms, turns and landmarks."""
    pts = np.asarray(path_m, dtype=np.float64)
    dense = _resample(pts, 0.25)
    rooms = [scene.room_at(p) for p in dense]
    room_type = {r.name: r.room_type for r in scene.rooms}
    # Runs of the same room; the two storeys of a stairwell count as one; corners clipped for less
    # than ~0.5 m are not worth a sentence.
    key = [None if r is None else ("staircase" if r.room_type == "staircase" else r.name) for r in rooms]
    runs: list[list] = []
    for i, k in enumerate(key):
        if k is None:
            continue
        if runs and runs[-1][0] == k:
            runs[-1][2] = i + 1
        else:
            runs.append([k, i, i + 1])
    runs = [r for j, r in enumerate(runs) if r[2] - r[1] >= 3 or j in (0, len(runs) - 1)]
    merged: list[list] = []
    for r in runs:
        if merged and merged[-1][0] == r[0]:
            merged[-1][2] = r[2]
        else:
            merged.append(list(r))
    seq = [(("staircase" if k == "staircase" else k), i0) for k, i0, _ in merged]
    room_type.setdefault("staircase", "staircase")
    seq_end = [i1 for _, _, i1 in merged]
    sentences: list[str] = []
    if len(pts) > 1:
        d0 = pts[1] - pts[0]
        first_dir = math.atan2(d0[1], d0[0])
    else:
        first_dir = start_heading_rad
    turn0 = _turn_word(first_dir - start_heading_rad)
    if seq:
        t0 = room_type[seq[0][0]]
        if len(seq) > 1:
            lead = f"{turn0.capitalize()} and exit the {t0}" if turn0 else f"Exit the {t0}"
        else:
            lead = f"{turn0.capitalize()} and walk through the {t0}" if turn0 else f"Walk through the {t0}"
        sentences.append(lead)
    used: set[int] = set()
    if goal_object is not None:
        used.add(goal_object.object_id)
    for k, (name, i0) in enumerate(seq[1:], start=1):
        seg = dense[i0 : seq_end[k]]
        # The turn taken on entering this room.
        turn = None
        if i0 >= 2 and i0 + 2 < len(dense):
            before = dense[i0] - dense[i0 - 2]
            after = dense[min(i0 + 4, len(dense) - 1)] - dense[i0]
            turn = _turn_word(math.atan2(after[1], after[0]) - math.atan2(before[1], before[0]))
        rt = room_type[name]
        prev_rt = room_type[seq[k - 1][0]]
        the = "the next" if rt == prev_rt else "the"
        if rt == "staircase":
            z0, z1 = dense[i0][2], dense[max(seq_end[k] - 1, i0)][2]
            phrase = "go up the stairs" if z1 > z0 else "go down the stairs"
        elif k == len(seq) - 1:
            phrase = f"enter {the} {rt}"
        else:
            phrase = f"go through {the} {rt}"
        if turn:
            phrase = f"{turn} and {phrase}"
        # A landmark passed in this room.
        mark = _landmark(scene, seg, name, used)
        if mark is not None and k < len(seq) - 1:
            phrase += f", walking past the {mark.description}"
            used.add(mark.object_id)
        sentences.append(phrase[0].upper() + phrase[1:])
    if goal_object is not None:
        goal_room = room_type.get(goal_object.room, "room")
        sentences.append(f"Stop next to the {goal_object.description} in the {goal_room}")
    else:
        last = room_type[seq[-1][0]] if seq else "room"
        sentences.append(f"Stop in the {last}")
    return ". ".join(sentences) + "."


def _landmark(scene: Scene, seg: np.ndarray, room: str, used: set[int]):
    best, best_d = None, 1.5
    for o in scene.objects:
        if o.room != room or o.object_id in used or o.label in ("painting", "rug", "chair"):
            continue
        if len(seg) == 0:
            continue
        d = float(np.min(np.linalg.norm(seg[:, :2] - np.array(o.position_m[:2]), axis=1)))
        if d < best_d:
            best, best_d = o, d
    return best


def _resample(pts: np.ndarray, spacing_m: float) -> np.ndarray:
    if len(pts) < 2:
        return pts.copy()
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    n = max(2, int(np.ceil(s[-1] / spacing_m)) + 1)
    q = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(q, s, pts[:, i]) for i in range(3)])


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


def copy_dataset(ds: EpisodeDataset) -> EpisodeDataset:
    return EpisodeDataset([Episode(copy.deepcopy(e.raw)) for e in ds.episodes], copy.deepcopy(ds.extra), list(ds.key_order))
