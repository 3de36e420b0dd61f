"""Published subsets: a seeded, stratified choice of episode ids that every user can reproduce and check."""

from __future__ import annotations

import gzip
import json
from collections import Counter
from pathlib import Path

import pytest

from evaluation.cli import main
from evaluation.dataset import (
    SUBSET_PRESETS, SUBSETS_DIR, Subset, SubsetMismatch, SubsetRule, allocate, episodes_digest, file_sha256,
    make_subset, select_subset,
)
from evaluation.errors import ConfigError
from libs.world import read_episodes

R2R = "r2r_ce/R2R_VLNCE_v1-3_preprocessed_val_unseen.json.gz"
LANGS = ("en-IN", "en-US", "hi-IN", "te-IN")


def rxr_like(path: Path, *, scenes: int = 11, per: tuple[int, ...] = (9, 14, 5, 3), shuffle: bool = False,
             str_ids: bool = False, edit=None) -> Path:
    """An RxR-CE-shaped val_unseen file (VLN-CE's RxR loader fields): ``instruction`` with ``language``,
    ``instruction_id``, ``annotator_id``, ``edit_distance``, ``timed_instruction``; 3 instructions per path.
    Scene k has ``per[lang] + k`` episodes in each language, so strata differ in size."""
    eps, eid = [], 0
    for k in range(scenes):
        scan = f"scan{k:02d}"
        for li, lang in enumerate(LANGS):
            for j in range(per[li] + k):
                eid += 1
                eps.append({
                    "episode_id": f"{eid}" if str_ids else eid, "trajectory_id": 10_000 * k + 100 * li + j // 3,
                    "scene_id": f"mp3d/{scan}/{scan}.glb", "start_position": [float(j), 0.1, -float(k)],
                    "start_rotation": [0.0, 0.0, 0.0, 1.0], "info": {"geodesic_distance": 7.5 + j % 5},
                    "goals": [{"position": [float(j) + 5.0, 0.1, -float(k)], "radius": 3.0}],
                    "reference_path": [[float(j), 0.1, -float(k)], [float(j) + 5.0, 0.1, -float(k)]],
                    "instruction": {"instruction_id": str(eid), "instruction_text": f"walk {lang} {eid}",
                                    "language": lang, "annotator_id": "7", "edit_distance": 0.1,
                                    "timed_instruction": [{"word": "walk", "start_time": 0.0, "end_time": 0.4}]},
                })
    if shuffle:
        eps = eps[1::2] + eps[0::2]
    if edit:
        edit(eps)
    with gzip.open(path, "wt", encoding="utf-8") as f:
        # dumps, not dump: the same text, from the C encoder in one write (dump encodes in Python, chunk by chunk)
        f.write(json.dumps({"episodes": eps}))  # RxR-CE files carry no instruction_vocab
    return path


@pytest.fixture(scope="module")
def rxr_file(tmp_path_factory) -> Path:
    """The default :func:`rxr_like` file, written once for the module (its tests only read it)."""
    return rxr_like(tmp_path_factory.mktemp("rxr") / "rxr.json.gz")


def test_allocation_gives_every_stratum_one_and_the_rest_by_size():
    q = allocate([300, 264, 255, 252, 177, 159, 141, 132, 102, 39, 18], 100)
    assert sum(q) == 100 and min(q) >= 1 and q == sorted(q, reverse=True)
    assert allocate([5, 5, 5], 2) in ([1, 1, 0],)  # fewer than the strata: ties go to the first ones
    assert allocate([1, 1, 50], 10) == [1, 1, 8]  # a stratum never gets more than it has
    with pytest.raises(ConfigError):
        allocate([3, 4], 8)


def test_rxr_subset_covers_every_scene_and_language_and_does_not_depend_on_file_order(rxr_file, tmp_path):
    rule = SUBSET_PRESETS["rxr-ce-val-unseen-195"]
    a = make_subset(rxr_file, rule, "rxr")
    b = make_subset(rxr_like(tmp_path / "b.json.gz", shuffle=True), rule, "rxr")
    assert len(a.episode_ids) == 195 and len(set(a.episode_ids)) == 195
    assert a.episode_ids == b.episode_ids and a.episodes_sha256 == b.episodes_sha256
    assert a.source_sha256 != b.source_sha256  # different bytes, same episodes
    eps = {e.episode_id: e for e in read_episodes(rxr_file).episodes}
    chosen = [eps[i] for i in a.episode_ids]
    strata = Counter((e.scene_id, e.raw["instruction"]["language"]) for e in chosen)
    assert len(strata) == 11 * 4  # every (scene, language) stratum is represented
    # Shares follow the file: en-US is the largest language, te-IN the smallest.
    assert a.languages["en-US"] > a.languages["en-IN"] > a.languages["hi-IN"] > a.languages["te-IN"] >= 11
    # One instruction per path while a stratum has paths left (3 per path here, strata of 3..24 episodes).
    for key, n in strata.items():
        paths = {e.raw["trajectory_id"] for e in eps.values() if (e.scene_id, e.raw["instruction"]["language"]) == key}
        chosen_paths = {e.raw["trajectory_id"] for e in chosen if (e.scene_id, e.raw["instruction"]["language"]) == key}
        assert len(chosen_paths) == min(n, len(paths)), key
    other = make_subset(rxr_file, SubsetRule(count=195, seed=1, strata=("scene", "language")))
    assert other.episode_ids != a.episode_ids


def test_english_only_and_string_ids(tmp_path):
    src = rxr_like(tmp_path / "rxr.json.gz", str_ids=True)
    en = make_subset(src, SUBSET_PRESETS["rxr-ce-val-unseen-195-en"], "en")
    assert set(en.languages) == {"en-IN", "en-US"} and sum(en.languages.values()) == 195
    assert all(isinstance(i, str) for i in en.episode_ids)
    assert en.episode_ids == sorted(en.episode_ids, key=int)  # digits as text sort as numbers
    with pytest.raises(ConfigError, match="no episode has a language"):
        make_subset(src, SubsetRule(count=5, languages=("fr",)))


def test_selection_is_pinned(tmp_path):
    """The rule's output on a fixed input: guards the ids against a numpy or Python change. (If numpy ever
    changes PCG64's doubles, every published subset would silently differ from what `subset` draws.)"""
    eps = read_episodes(rxr_like(tmp_path / "x.json.gz", scenes=2, per=(3, 4, 2, 2))).episodes
    ids = select_subset(eps, SubsetRule(count=9, seed=0, strata=("scene", "language")))
    assert ids == PINNED


PINNED = [3, 4, 9, 11, 12, 16, 19, 21, 26]


def test_apply_runs_exactly_the_subset_and_refuses_other_files(rxr_file, tmp_path):
    src = rxr_file
    sub = make_subset(src, SubsetRule(count=30, strata=("scene", "language")), "s30")
    path = sub.write(tmp_path / "s30.json")
    back = Subset.read(path)
    assert back.episode_ids == sub.episode_ids and back.rule == sub.rule
    eps = read_episodes(src).episodes
    assert [e.episode_id for e in back.apply(eps, src)] == sorted(sub.episode_ids)
    # Extra fields (tokens, say) and another compression do not matter; the same ids on other episodes do.
    extra = rxr_like(tmp_path / "extra.json.gz",
                     edit=lambda es: [e["instruction"].update(instruction_tokens=[1, 2]) for e in es])
    assert len(back.apply(read_episodes(extra).episodes, extra)) == 30
    moved = rxr_like(tmp_path / "moved.json.gz", edit=lambda es: [e["goals"][0]["position"].__setitem__(0, 99.0)
                                                                  for e in es])
    with pytest.raises(SubsetMismatch, match="not the same episodes"):
        back.apply(read_episodes(moved).episodes, moved)
    fewer = [e for e in eps if e.episode_id != sub.episode_ids[3]]
    with pytest.raises(SubsetMismatch, match=f"1 of its 30 episodes are not in .*first: {sub.episode_ids[3]}"):
        back.apply(fewer)


def test_cli_subset_then_run_estimates_exactly_those_episodes(rxr_file, tmp_path, capsys):
    src = rxr_file
    out = tmp_path / "sub.json"
    assert main(["subset", "--dataset", str(src), "--count", "25", "--seed", "3", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["strata"] == ["scene", "language"]  # languages stratified by default when present
    assert doc["count"] == 25 and doc["seed"] == 3 and doc["source"]["sha256"] == file_sha256(src)
    assert "25 of" in capsys.readouterr().out
    assert main(["run", "--episodes", str(src), "--subset", str(out), "--estimate"]) == 0
    assert "estimate for 25 episodes" in capsys.readouterr().out
    # A file without the subset's episodes is refused before anything runs.
    other = rxr_like(tmp_path / "small.json.gz", scenes=2)
    assert main(["run", "--episodes", str(other), "--subset", str(out), "--estimate"]) == 2
    assert "23 of its 25 episodes are not in" in capsys.readouterr().err
    assert main(["subset", "--dataset", str(src), "--preset", "nope", "--out", str(out)]) == 2


def test_published_r2r_subset_is_what_the_rule_draws_from_val_unseen(shared_data):
    src = shared_data / R2R
    if not src.is_file():
        pytest.skip(f"{src} absent")
    published = Subset.read("r2r-ce-val-unseen-100")
    assert published.source_sha256 == file_sha256(src) and published.source_name == src.name
    drawn = make_subset(src, SUBSET_PRESETS["r2r-ce-val-unseen-100"], "r2r-ce-val-unseen-100")
    assert drawn.episode_ids == published.episode_ids and drawn.episodes_sha256 == published.episodes_sha256
    assert len(published.episode_ids) == 100 and len(published.scenes) == 11  # all val_unseen scans
    chosen = published.apply(read_episodes(src).episodes, src)
    assert len({e.raw["trajectory_id"] for e in chosen}) == 100  # 100 distinct paths
    assert episodes_digest(chosen) == published.episodes_sha256
    assert (SUBSETS_DIR / "r2r-ce-val-unseen-100.json").read_text() == drawn.to_json()
