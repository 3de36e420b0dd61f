"""bench.ablation: every variant on the same episodes, one map build per kind, resumable."""

from __future__ import annotations

import json

import pytest

from bench import ablation, agent_maps
from evaluation.presets import Variant
from evaluation.runner import RunConfig


def test_a_reconstructed_variant_runs_once_per_map_kind_and_curated_once():
    variants = (Variant("curated", {"map_source": "curated"}), Variant("reconstructed", {"map_source": "reconstructed"}))
    v, c, k = ablation.expand_map_kinds(variants, RunConfig(), ["rgbd", "noisy"])
    assert [x.label for x in v] == ["curated", "reconstructed (rgbd)", "reconstructed (noisy)"]
    assert k == ["curated", "rgbd", "noisy"] and [x.map_source for x in c] == ["curated", "reconstructed", "reconstructed"]
    v, _, k = ablation.expand_map_kinds(variants, RunConfig(), ["mono-sim"])
    assert [x.label for x in v] == ["curated", "reconstructed"] and k == ["curated", "mono-sim"]


def test_map_kinds_are_checked():
    assert ablation._map_kinds("rgbd, noisy") == ["rgbd", "noisy"]
    for bad in ("", "rgbd,rgbd", "lidar"):
        with pytest.raises(Exception, match="map kinds"):
            ablation._map_kinds(bad)


def test_views_preset_pairs_every_variant_and_resumes(tmp_path, monkeypatch):
    monkeypatch.setattr(agent_maps, "MAPS", tmp_path / "maps")
    argv = ["--preset", "views", "--houses", "1", "--per-house", "2", "--area-m2", "40", "--max-steps", "4",
            "--out", str(tmp_path / "out")]
    first = ablation.main(argv)
    assert first["n"] == 2
    root = tmp_path / "out" / "views" / "rgbd" / "seed0-1x2-floors12-area40"
    runs = {d.name: [json.loads(line) for line in (d / "results.jsonl").read_text().splitlines()]
            for d in root.iterdir() if d.is_dir()}
    assert set(runs) == {"without_anticipation", "map_views_visibility_splat", "map_views_paper_splat",
                         "true-scene_views"}
    for name, rows in runs.items():
        assert sorted(r["episode_id"] for r in rows) == ["1", "2"] and all(r["status"] == "done" for r in rows)
        assert all(r["options"]["anticipation"] == (name != "without_anticipation") for r in rows)
    modes = {r["options"].get("anticipation_splat_mode") for r in runs["map_views_paper_splat"]}
    assert modes == {"paper"}
    assert (root / "table.md").read_text().count("| SR |") == 3  # three variants against the first
    assert len(list((tmp_path / "maps").glob("*.ply"))) == 1  # one rgbd map, built once for every variant
    _a_map_of_other_code_is_rebuilt(tmp_path / "maps", monkeypatch)
    ablation.main(argv)  # resumes: nothing left to run, nothing appended
    for name, rows in runs.items():
        assert len((root / name / "results.jsonl").read_text().splitlines()) == len(rows)
    # One variant of the preset (a confirmation on another set): its own folder, paired elsewhere.
    one = ablation.main(argv + ["--variants", "true-scene views"])
    assert one["n"] == 2 and 0.0 <= one["sr"] <= 100.0
    assert len((root / "true-scene_views" / "results.jsonl").read_text().splitlines()) == 2
    with pytest.raises(SystemExit):
        ablation.main(argv + ["--variants", "hfov 45"])
    # Only some scenes (a bisection re-runs the houses where two codes differ): a scene the set has not is
    # refused by name; the house's own scene keeps its episodes.
    scene = runs["true-scene_views"][0]["scene_id"]
    assert ablation.main(argv + ["--scenes", scene])["n"] == 2
    with pytest.raises(SystemExit):
        ablation.main(argv + ["--scenes", "generated:99"])
    # A second set (its ids repeat the first's): its own folder, and both sets' pairs pooled.
    both = ablation.main(argv + ["--variants", "true-scene views", "--seeds", "0", "1"])
    assert both["sets"] == 2 and both["n"] == 4
    second = tmp_path / "out" / "views" / "rgbd" / "seed1-1x2-floors12-area40" / "true-scene_views"
    rows = [json.loads(line) for line in (second / "results.jsonl").read_text().splitlines()]
    assert sorted(r["episode_id"] for r in rows) == ["1", "2"]
    assert {r["scene_id"] for r in rows}.isdisjoint({r["scene_id"] for r in runs["true-scene_views"]})
    with pytest.raises(SystemExit):
        ablation.main(argv + ["--seeds", "1", "1"])


def test_a_log_of_another_set_is_refused_not_resumed(tmp_path, capsys):
    """Episode ids repeat from set to set: results of another set found in a set's folder (moved there, or
    the generator drawing the set differently) stop the run with the folder named, and stay as they were."""
    argv = ["--preset", "views", "--houses", "1", "--per-house", "2", "--area-m2", "40", "--max-steps", "4",
            "--out", str(tmp_path / "out"), "--variants", "without anticipation"]
    log = tmp_path / "out" / "views" / "rgbd" / "seed0-1x2-floors12-area40" / "without_anticipation" / "results.jsonl"
    log.parent.mkdir(parents=True)
    other = {"episode_id": "1", "scene_id": "generated:1000", "status": "done", "instruction": "Go to the sofa."}
    log.write_text(json.dumps(other) + "\n")
    with pytest.raises(SystemExit):
        ablation.main(argv)
    assert "is not this set's" in capsys.readouterr().err
    assert log.read_text() == json.dumps(other) + "\n"


def _a_map_of_other_code_is_rebuilt(maps, monkeypatch):
    """The cached map records the mapping code that built it; served while that code is today's, rebuilt
    (from the exploration still held in memory) once it is not."""
    (ply,) = maps.glob("*.ply")
    assert agent_maps.build_record_at(ply)["code"] == agent_maps.map_code_version()
    (spec, noise, *_), = agent_maps._RECORDINGS  # the exploration the map was built from
    stamp = ply.stat().st_mtime_ns
    robot, _ = agent_maps.build_map(spec, "rgbd", noise)
    robot.close()
    assert ply.stat().st_mtime_ns == stamp  # same code: the cache
    monkeypatch.setattr(agent_maps, "_CODE_VERSION", "0123456789ab")  # as if the mapper had changed since
    robot, _ = agent_maps.build_map(spec, "rgbd", noise)
    robot.close()
    assert ply.stat().st_mtime_ns != stamp and agent_maps.build_record_at(ply)["code"] == "0123456789ab"
