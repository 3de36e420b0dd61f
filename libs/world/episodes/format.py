"""The VLN-CE episode and ground-truth file formats (R2R-CE / RxR-CE), read and written exactly.

The file format is VLN-CE's: ``{"episodes": [...], "instruction_vocab": {...}}`` (gzip JSON), each
episode with ``episode_id``, ``trajectory_id``, ``scene_id``, ``start_position`` and
``reference_path`` / goal ``position`` in Habitat coordinates (**y up**), ``start_rotation`` as a
quaternion ``[x, y, z, w]``, ``info.geodesic_distance``, ``goals[{position, radius}]`` and
``instruction{instruction_text, instruction_tokens}`` (RxR-CE adds fields such as ``language``;
they are kept). The ground-truth file ``*_gt.json.gz`` (keyed by ``str(episode_id)``: dense
``locations``, discrete ``actions``, ``forward_steps``) is read and written by
:func:`read_ground_truth` / :func:`write_ground_truth`.
:class:`Episode` keeps the raw record, so a read-write round trip is exact to the
byte of the JSON text, and exposes world-frame (z-up) views through properties: this module is
the one place where episode positions are converted from Habitat coordinates.
"""

from __future__ import annotations

import gzip
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.geometry import habitat_quaternion_to_heading, habitat_to_world, heading_to_habitat_quaternion, world_to_habitat
from shared.schemas import Pose

from ..errors import EpisodeFormatError, SceneNotFoundError
from ..scene import is_generated_spec, resolve_scene_path

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


def _read_json(path: Path, what: str):
    """A ``.json.gz`` or ``.json`` document; a missing file or bad JSON is a clear error."""
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", encoding="utf-8") as f:
        try:
            return json.load(f)
        except json.JSONDecodeError as exc:
            raise EpisodeFormatError(f"{path}: not JSON ({exc})") from None


def read_episodes(path: Path | str) -> EpisodeDataset:
    """Read an R2R-CE / RxR-CE ``.json.gz`` (or plain ``.json``) episode file."""
    path = Path(path)
    doc = _read_json(path, "episode file")
    if not isinstance(doc, dict) or not isinstance(doc.get("episodes"), list):
        raise EpisodeFormatError(f"{path}: expected an object with an 'episodes' list")
    episodes = [Episode(e) for e in doc["episodes"]]
    extra = {k: v for k, v in doc.items() if k != "episodes"}
    return EpisodeDataset(episodes, extra, list(doc.keys()))


def write_episodes(dataset: EpisodeDataset, path: Path | str) -> Path:
    """Write a dataset; ``.gz`` paths are gzip-compressed (mtime 0, so the bytes are reproducible)."""
    return _write_json(dataset.to_json(), Path(path))


# --- ground truth (``*_gt.json.gz``) ---------------------------------------------------------------

STOP, MOVE_FORWARD, TURN_LEFT, TURN_RIGHT = 0, 1, 2, 3  # VLN-CE discrete actions


@dataclass
class GroundTruth:
    """One episode's ground-truth shortest-path record of a VLN-CE ``*_gt.json.gz`` file.

    ``raw`` is the record exactly as in the file: ``locations`` (Habitat frame, y up; the start,
    then the position after every forward step), ``actions`` (0 stop, 1 forward 0.25 m, 2 left
    15 deg, 3 right 15 deg) and ``forward_steps``.
    """

    raw: dict[str, Any]

    def __post_init__(self) -> None:
        missing = [k for k in ("locations", "actions", "forward_steps") if k not in self.raw]
        if missing:
            raise EpisodeFormatError(f"ground-truth record lacks {', '.join(missing)}")

    @property
    def locations_m(self) -> np.ndarray:
        """(N, 3) world-frame (z-up) positions."""
        return habitat_to_world(np.asarray(self.raw["locations"], dtype=np.float64).reshape(-1, 3))

    @property
    def actions(self) -> list[int]:
        return list(self.raw["actions"])

    @property
    def forward_steps(self) -> int:
        return int(self.raw["forward_steps"])

    @classmethod
    def from_world(cls, locations_m: np.ndarray, actions: list[int]) -> GroundTruth:
        locs = np.asarray(locations_m, dtype=np.float64).reshape(-1, 3)
        acts = [int(a) for a in actions]
        if acts.count(MOVE_FORWARD) != len(locs) - 1:
            raise EpisodeFormatError(f"{len(locs)} locations for {acts.count(MOVE_FORWARD)} forward steps")
        return cls({
            "locations": [[float(v) for v in world_to_habitat(p)] for p in locs],
            "actions": acts,
            "forward_steps": acts.count(MOVE_FORWARD),
        })


def read_ground_truth(path: Path | str) -> dict[str, GroundTruth]:
    """Read a VLN-CE ground-truth file, keyed by ``str(episode_id)`` in file order."""
    path = Path(path)
    doc = _read_json(path, "ground-truth file")
    if not isinstance(doc, dict):
        raise EpisodeFormatError(f"{path}: expected an object keyed by episode id")
    return {k: GroundTruth(v) for k, v in doc.items()}


def write_ground_truth(records: dict[Any, GroundTruth], path: Path | str) -> Path:
    """Write ground-truth records (keys become ``str(episode_id)``); byte-exact for a file read here."""
    doc = {str(k): v.raw for k, v in records.items()}
    return _write_json(json.dumps(doc), Path(path))


def _write_json(text: str, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = text.encode("utf-8")
    if path.suffix == ".gz":
        # mtime 0 and no file name: the same content always gives the same bytes.
        with open(path, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as f:
            f.write(data)
    else:
        path.write_bytes(data)
    return path
