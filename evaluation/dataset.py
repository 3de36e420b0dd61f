"""The generated evaluation set: R2R-CE-format episodes over several procedural houses.

The repository ships this generator, not the file: ``python -m evaluation generate --out FILE
--houses 5 --per-house 20 --floors 1,2 --seed 0`` writes the same bytes on every machine (the houses,
nav grids and episode sampling are seeded; gzip is written with mtime 0). Beside the episodes it
writes VLN-CE's ground-truth file (``<name>_gt.json.gz``: dense 0.25 m oracle locations), which the
runner uses as the nDTW reference, exactly as VLN-CE does.
"""

from __future__ import annotations

import logging
from contextlib import closing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evaluation.errors import ConfigError
from services.robot_io.core import (
    EpisodeDataset, GroundTruth, SimConfig, SimRobot, generate_episodes, ground_truth_for, write_episodes,
    write_ground_truth,
)
from services.robot_io.core.episodes import build_vocab, tokens_for
from services.robot_io.core.house import HouseSpec

log = logging.getLogger(__name__)


def gt_path_for(episodes_path: Path | str) -> Path:
    """VLN-CE's naming: ``X.json.gz`` -> ``X_gt.json.gz`` (``X.json`` -> ``X_gt.json``)."""
    p = Path(episodes_path)
    name = p.name
    for suffix in (".json.gz", ".json"):
        if name.endswith(suffix):
            return p.with_name(name[: -len(suffix)] + "_gt" + suffix)
    raise ConfigError(f"{p}: an episode file ends with .json.gz or .json")


@dataclass(frozen=True)
class SetSpec:
    """What to generate. House ``i`` is ``generated:<seed*1000+i>`` with ``floors[i % len(floors)]`` floors."""

    houses: int = 5
    per_house: int = 20
    floors: tuple[int, ...] = (1, 2)
    seed: int = 0
    area_m2: float | None = None  # None: the house generator's default
    min_geodesic_m: float = 5.0
    max_geodesic_m: float = 20.0
    sim: dict[str, Any] = field(default_factory=dict)  # SimConfig overrides: must match robot-io's config

    def __post_init__(self) -> None:
        if self.houses < 1 or self.per_house < 1:
            raise ConfigError("houses and per_house must be at least 1")
        if not self.floors or any(f not in (1, 2) for f in self.floors):
            raise ConfigError(f"floors must be a non-empty list of 1 and/or 2, got {self.floors}")
        if not 0 < self.min_geodesic_m < self.max_geodesic_m:
            raise ConfigError("need 0 < min_geodesic_m < max_geodesic_m")

    def scene_specs(self) -> list[str]:
        out = []
        for i in range(self.houses):
            kw: dict[str, Any] = {"seed": self.seed * 1000 + i, "floors": self.floors[i % len(self.floors)]}
            if self.area_m2 is not None:
                kw["area_m2"] = self.area_m2
            out.append(HouseSpec(**kw).spec)
        return out


def generate_set(spec: SetSpec, *, with_gt: bool = True,
                 progress: Callable[[int, int, str], None] | None = None,
                 ) -> tuple[EpisodeDataset, dict[str, GroundTruth]]:
    """Episodes (ids 1..N, house by house) and, with ``with_gt``, their ground-truth records.

    The nav grid is the simulator's own (a :class:`SimRobot` with ``spec.sim``), so start, goal and
    geodesic distances are the ones robot-io will measure when the episodes run.
    """
    episodes, gt = [], {}
    scenes = spec.scene_specs()
    for i, scene in enumerate(scenes):
        if progress:
            progress(i, len(scenes), scene)
        cfg = SimConfig.model_validate({"camera": {"width_px": 64, "height_px": 64}, **spec.sim, "scene": scene})
        with closing(SimRobot(cfg)) as robot:
            ds = generate_episodes(robot.scene, robot.nav, spec.per_house, seed=spec.seed * 1000 + i,
                                   min_geodesic_m=spec.min_geodesic_m, max_geodesic_m=spec.max_geodesic_m,
                                   first_episode_id=1 + i * spec.per_house)
            for e in ds.episodes:
                e.raw["scene_id"] = scene  # the spec robot-io loads, whatever name the house reports
            if with_gt:
                gt.update(ground_truth_for(ds, robot.nav))
        episodes.extend(ds.episodes)
        log.info("%s: %d episodes", scene, len(ds.episodes))
    # One vocabulary over the whole set (R2R-CE has one per split); tokens re-indexed against it.
    vocab = build_vocab([e.instruction for e in episodes])
    for e in episodes:
        e.raw["instruction"]["instruction_tokens"] = tokens_for(e.instruction, vocab)
    return EpisodeDataset(episodes, {"instruction_vocab": vocab}), gt


def write_set(dataset: EpisodeDataset, gt: dict[str, GroundTruth], path: Path | str) -> list[Path]:
    """Write the episode file and, when ``gt`` is not empty, its ``_gt`` file beside it."""
    out = [write_episodes(dataset, path)]
    if gt:
        out.append(write_ground_truth(gt, gt_path_for(path)))
    return out


def parse_floors(text: str | Sequence[int]) -> tuple[int, ...]:
    if isinstance(text, str):
        try:
            return tuple(int(x) for x in text.split(",") if x.strip())
        except ValueError:
            raise ConfigError(f"floors must be like '1,2', got {text!r}") from None
    return tuple(int(x) for x in text)
