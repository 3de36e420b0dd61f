"""The generated evaluation set: R2R-CE-format episodes over several procedural houses.

The repository ships this generator, not the file: ``python -m evaluation generate --out FILE
--houses 5 --per-house 20 --floors 1,2 --seed 0`` writes the same bytes on every machine (the houses,
nav grids and episode sampling are seeded; gzip is written with mtime 0). Beside the episodes it
writes VLN-CE's ground-truth file (``<name>_gt.json.gz``: dense 0.25 m oracle locations), which the
runner uses as the nDTW reference, exactly as VLN-CE does.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections import Counter
from contextlib import closing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evaluation.errors import ConfigError
from libs.world import EpisodeDataset, GroundTruth, generate_episodes, ground_truth_for, write_episodes, write_ground_truth
from libs.world.episodes import build_vocab, tokens_for
from libs.world.house import HouseSpec

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
    # The simulator (and its renderer's open3d) only for generating: `run` reads subsets and ground truth
    # through this module and should start in a fraction of a second.
    from services.robot_io.core import SimConfig, SimRobot

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


# --- published subsets --------------------------------------------------------------------------------
# Zero-shot MLLM agents are evaluated on a sample of val_unseen (the paper: 100 R2R-CE and 195 RxR-CE
# episodes), and a number on a sample means something only when everyone uses the same sample. A subset
# is therefore a file of episode ids, drawn by a documented rule from a named source file (its sha256 and
# a digest of the chosen episodes' content), committed under evaluation/subsets/ and checked when a run
# uses it (``evaluation run --subset``).

SUBSET_RULE = "stratified-v1"
SUBSET_RULE_TEXT = (
    "stratified-v1: keep the episodes whose instruction language matches one of `languages` (a prefix: "
    "'en' matches en-US and en-IN; all when null); group them into strata by the `strata` fields (scene_id, "
    "instruction language), strata in sorted order; give each stratum one episode when count >= the number "
    "of strata, the rest in proportion to the episodes each stratum has left, by largest remainder (ties: stratum order); inside a "
    "stratum sort the episode ids (numerically when they are numbers), draw one float per id from numpy.random.default_rng(seed) (PCG64: "
    "strata in order, one rng for all), order the ids by those floats and take them in that order, at most "
    "one episode per trajectory_id until every trajectory of the stratum is used; the ids are listed sorted.")
SUBSETS_DIR = Path(__file__).resolve().parent / "subsets"
STRATA_FIELDS = ("scene", "language")


class SubsetMismatch(ConfigError):
    """A subset's episodes are not in the episode file, or not the episodes the subset was drawn from."""


@dataclass(frozen=True)
class SubsetRule:
    """How a subset is drawn; the presets below are the published ones."""

    count: int
    seed: int = 0
    strata: tuple[str, ...] = ("scene",)
    languages: tuple[str, ...] | None = None  # language prefixes to keep (None: every language)
    one_per_trajectory: bool = True  # R2R has 3 instructions per path: prefer distinct paths

    def __post_init__(self) -> None:
        if self.count < 1:
            raise ConfigError(f"a subset needs count >= 1, got {self.count}")
        unknown = [s for s in self.strata if s not in STRATA_FIELDS]
        if unknown:
            raise ConfigError(f"unknown stratum field {unknown[0]!r}; known: {', '.join(STRATA_FIELDS)}")


# The published rules; a subset drawn with one is written to SUBSETS_DIR/<name>.json (RxR-CE's file is not
# distributed with this repository: its subsets are drawn where a user has it).
SUBSET_PRESETS: dict[str, SubsetRule] = {
    "r2r-ce-val-unseen-100": SubsetRule(count=100, seed=0, strata=("scene",)),
    "rxr-ce-val-unseen-195": SubsetRule(count=195, seed=0, strata=("scene", "language")),
    "rxr-ce-val-unseen-195-en": SubsetRule(count=195, seed=0, strata=("scene", "language"), languages=("en",)),
}


def episode_language(e) -> str | None:
    """RxR-CE's ``instruction.language`` (en-US, en-IN, hi-IN, te-IN); None for R2R-CE."""
    lang = (e.raw.get("instruction") or {}).get("language")
    return None if lang is None else str(lang)


def _id_key(episode_id) -> tuple[int, int, str]:
    """Ids that are numbers (R2R-CE's ints, or digits as text) sort numerically, others as text after them;
    never by hash."""
    if isinstance(episode_id, int) and not isinstance(episode_id, bool):
        return (0, episode_id, "")
    text = str(episode_id)
    return (0, int(text), text) if text.isdigit() else (1, 0, text)


def _stratum(e, fields: Sequence[str]) -> tuple[str, ...]:
    return tuple(e.scene_id if f == "scene" else (episode_language(e) or "") for f in fields)


def allocate(sizes: Sequence[int], count: int) -> list[int]:
    """Quota per stratum: one each when possible, the rest proportional to size (largest remainder)."""
    total = sum(sizes)
    if count > total:
        raise ConfigError(f"a subset of {count} from {total} episodes")
    base = [1 if count >= len(sizes) else 0 for _ in sizes]
    rest, room = count - sum(base), [s - b for s, b in zip(sizes, base)]
    room_total = sum(room)
    exact = [rest * r / room_total if room_total else 0.0 for r in room]
    quota = [b + min(int(x), r) for b, x, r in zip(base, exact, room)]
    # Largest remainder first; ties go to the earlier stratum (sorted order), never to chance.
    order = sorted(range(len(sizes)), key=lambda i: (-(exact[i] - int(exact[i])), i))
    while sum(quota) < count:
        for i in order:
            if sum(quota) < count and quota[i] < sizes[i]:
                quota[i] += 1
    return quota


def select_subset(episodes: Sequence, rule: SubsetRule) -> list:
    """The ids :data:`SUBSET_RULE_TEXT` describes, sorted (the same on every machine and Python)."""
    import numpy as np

    eps = [e for e in episodes if rule.languages is None
           or any((episode_language(e) or "").startswith(p) for p in rule.languages)]
    ids = [str(e.episode_id) for e in eps]
    if len(set(ids)) != len(ids):
        raise ConfigError("the episode file repeats episode ids; a subset names episodes by id")
    if not eps:
        raise ConfigError(f"no episode has a language in {list(rule.languages or [])}")
    groups: dict[tuple[str, ...], list] = {}
    for e in eps:
        groups.setdefault(_stratum(e, rule.strata), []).append(e)
    keys = sorted(groups)
    quotas = allocate([len(groups[k]) for k in keys], rule.count)
    rng = np.random.default_rng(rule.seed)
    chosen = []
    for k, quota in zip(keys, quotas):
        members = sorted(groups[k], key=lambda e: _id_key(e.episode_id))
        # rng.random is PCG64's 53-bit doubles: stable across numpy versions, unlike choice/permutation.
        draws = rng.random(len(members))
        ordered = [members[i] for i in np.argsort(draws, kind="stable")]
        picked, seen, later = [], set(), []
        for e in ordered:
            traj = e.raw.get("trajectory_id", e.episode_id) if rule.one_per_trajectory else e.episode_id
            (later if traj in seen else picked).append(e)
            seen.add(traj)
        chosen.extend((picked + later)[:quota])
    return sorted((e.episode_id for e in chosen), key=_id_key)


def episodes_digest(episodes: Sequence) -> str:
    """sha256 of what makes the episodes the same task (ids, scene, start, goals, path, instruction text),
    in id order: insensitive to the file's compression, key order and extra fields (tokens, say)."""
    rows = []
    for e in sorted(episodes, key=lambda e: _id_key(e.episode_id)):
        r = e.raw
        rows.append([r["episode_id"], r["scene_id"], r["start_position"], r["start_rotation"],
                     [g.get("position") for g in r["goals"]], r.get("reference_path"), e.instruction,
                     episode_language(e)])
    return hashlib.sha256(json.dumps(rows, separators=(",", ":")).encode()).hexdigest()


def file_sha256(path: Path | str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class Subset:
    """A published subset: the ids, the rule and seed that chose them, and what they were drawn from."""

    name: str
    episode_ids: list
    rule: SubsetRule
    source_name: str
    source_sha256: str
    source_episodes: int
    episodes_sha256: str
    scenes: dict[str, int] = field(default_factory=dict)
    languages: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> str:
        doc = {
            "name": self.name, "rule": SUBSET_RULE, "rule_text": SUBSET_RULE_TEXT,
            "count": len(self.episode_ids), "seed": self.rule.seed, "strata": list(self.rule.strata),
            "languages_kept": None if self.rule.languages is None else list(self.rule.languages),
            "one_per_trajectory": self.rule.one_per_trajectory,
            "source": {"name": self.source_name, "sha256": self.source_sha256, "episodes": self.source_episodes},
            "episodes_sha256": self.episodes_sha256, "scenes": self.scenes, "languages": self.languages,
            "episode_ids": self.episode_ids,
        }
        return json.dumps(doc, indent=1) + "\n"

    def write(self, path: Path | str) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(self.to_json(), encoding="utf-8")
        return p

    @classmethod
    def read(cls, path_or_name: Path | str) -> Subset:
        """A subset file, or the name of a published one (``r2r-ce-val-unseen-100``)."""
        p = Path(path_or_name)
        if not p.is_file() and (SUBSETS_DIR / f"{path_or_name}.json").is_file():
            p = SUBSETS_DIR / f"{path_or_name}.json"
        if not p.is_file():
            published = sorted(x.stem for x in SUBSETS_DIR.glob("*.json"))
            raise ConfigError(f"subset not found: {path_or_name} (published: {', '.join(published) or 'none'})")
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
            if doc.get("rule") != SUBSET_RULE:
                raise ConfigError(f"{p}: subset rule {doc.get('rule')!r}, this version reads {SUBSET_RULE!r}")
            ids = doc["episode_ids"]
            if not isinstance(ids, list) or not ids or len({str(i) for i in ids}) != len(ids):
                raise ConfigError(f"{p}: episode_ids must be a non-empty list without repeats")
            langs = doc.get("languages_kept")
            rule = SubsetRule(count=len(ids), seed=int(doc["seed"]), strata=tuple(doc["strata"]),
                              languages=None if langs is None else tuple(langs),
                              one_per_trajectory=bool(doc.get("one_per_trajectory", True)))
            src = doc["source"]
            return cls(str(doc["name"]), ids, rule, str(src["name"]), str(src["sha256"]), int(src["episodes"]),
                       str(doc["episodes_sha256"]), dict(doc.get("scenes", {})), dict(doc.get("languages", {})))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError(f"{p}: not a subset file ({exc!r})") from None

    def apply(self, episodes: Sequence, source: Path | str | None = None) -> list:
        """The file's episodes that the subset names, in the file's order; refuses a file they are not in.

        Checked: every id is present (else :class:`SubsetMismatch` naming the missing ids) and the chosen
        episodes' content digest is the published one (same ids in a different file - R2R-CE's
        val_seen, a re-generated set - are different episodes). A different file hash alone (recompressed,
        extra fields) is only logged.
        """
        by_id = {str(e.episode_id): e for e in episodes}
        missing = [i for i in self.episode_ids if str(i) not in by_id]
        where = f"{source}" if source else "the episode file"
        if missing:
            raise SubsetMismatch(
                f"subset {self.name}: {len(missing)} of its {len(self.episode_ids)} episodes are not in {where} "
                f"(first: {', '.join(map(str, missing[:5]))}); it was drawn from {self.source_name} "
                f"(sha256 {self.source_sha256[:12]}...)")
        wanted = {str(i) for i in self.episode_ids}
        chosen = [e for e in episodes if str(e.episode_id) in wanted]
        digest = episodes_digest(chosen)
        if digest != self.episodes_sha256:
            raise SubsetMismatch(
                f"subset {self.name}: {where} has its {len(chosen)} episode ids but not the same episodes "
                f"(content sha256 {digest[:12]}..., the subset's {self.episodes_sha256[:12]}...); it was drawn "
                f"from {self.source_name} (sha256 {self.source_sha256[:12]}...)")
        if source is not None and Path(source).is_file() and file_sha256(source) != self.source_sha256:
            log.info("%s differs from %s byte for byte, but the subset's %d episodes are identical", source,
                     self.source_name, len(chosen))
        return chosen


def make_subset(path: Path | str, rule: SubsetRule, name: str | None = None) -> Subset:
    """Draw a subset from an episode file (R2R-CE / RxR-CE ``.json.gz``)."""
    from libs.world import read_episodes

    path = Path(path)
    eps = read_episodes(path).episodes
    ids = select_subset(eps, rule)
    wanted = {str(i) for i in ids}
    chosen = [e for e in eps if str(e.episode_id) in wanted]
    scenes = dict(sorted(Counter(e.scene_id for e in chosen).items()))
    langs = dict(sorted(Counter(episode_language(e) for e in chosen if episode_language(e)).items()))
    return Subset(name or f"{path.name.split('.')[0]}-{len(ids)}-seed{rule.seed}", ids, rule, path.name,
                  file_sha256(path), len(eps), episodes_digest(chosen), scenes, langs)
