"""Presets (table + plot per comparison) and the command line."""

from __future__ import annotations

import csv

import pytest
from PIL import Image

from tests.unit.evaluation.conftest import box_scene
from evaluation.cli import build_parser, main, run_config
from evaluation.errors import ConfigError
from evaluation.presets import presets, run_preset
from evaluation.runner import SceneMapIndex, MapSource, RunConfig


def test_presets_mirror_the_paper(monkeypatch):
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    monkeypatch.delenv("ANT_OPENAI_BASE_URL", raising=False)
    p = presets()
    assert set(p) == {"cloud", "anticipation", "views", "hfov", "policies", "scene-graph", "scene-graph-anticipation"}
    assert [v.overrides["policy_config"]["scene_graph"] for v in p["scene-graph"].variants] == [False, True]
    assert [v.overrides["anticipation"] for v in p["scene-graph-anticipation"].variants] == [False, True]
    views = p["views"].variants
    assert [v.overrides["anticipation"] for v in views] == [False, True, True, True]
    assert [(v.overrides.get("anticipation_views"), v.overrides.get("anticipation_splat_mode")) for v in views[1:]] \
        == [("map", "visibility"), ("map", "paper"), ("true-scene", None)]
    assert [v.overrides["map_source"] for v in p["cloud"].variants] == ["curated", "reconstructed"]
    assert [v.overrides["anticipation_hfov_deg"] for v in p["hfov"].variants] == [60.0, 90.0, 120.0]
    assert [v.overrides["anticipation"] for v in p["anticipation"].variants] == [True, False]
    assert [v.label for v in p["policies"].variants] == ["heuristic", "oracle"]
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test")
    assert [v.label for v in presets()["policies"].variants] == ["heuristic", "oracle", "openai"]
    # The MLLM's scene-graph ablation exists only with an LLM configured ("all" never starts a paid run).
    mllm = presets()["scene-graph-mllm"].variants
    assert [(v.overrides["policy"], v.overrides["policy_config"]["scene_graph"]) for v in mllm] \
        == [("openai", False), ("openai", True)]


def test_hfov_preset_runs_every_variant_and_writes_table_and_plot(world, gateway, episodes, tmp_path):
    with gateway() as gw:
        rep = run_preset("hfov", episodes, None, RunConfig(poll_s=0.01, plots=False), tmp_path, gw, world.robot,
                         map_cache=SceneMapIndex(tmp_path / "maps.json"), progress=False)
    hfovs = sorted({r.options.anticipation_hfov_deg for r in world.planner.requests})
    assert hfovs == [60.0, 90.0, 120.0] and len(world.planner.requests) == 3 * 4
    assert len(world.reconstructor.maps) == 2  # maps shared by the variants
    rows = list(csv.DictReader(rep.table_csv.open()))
    assert [r["label"] for r in rows] == ["hfov 60", "hfov 90", "hfov 120"]
    assert all(r["count"] == "4" and r["skipped"] == "1" for r in rows)
    assert "HFOV 90 deg beats" in rep.table_md.read_text()
    with Image.open(rep.plot_png) as im:
        assert im.size[0] > 400 and im.size[1] > 300
    for v in rep.preset.variants:
        assert (tmp_path / "hfov" / v.slug / "results.jsonl").is_file()


def test_cloud_preset_uses_both_sources(world, gateway, episodes, tmp_path, monkeypatch):
    import evaluation.runner as runner_mod

    monkeypatch.setattr(runner_mod.EvalRunner, "__init__", _with_builder(runner_mod.EvalRunner.__init__))
    with gateway() as gw:
        # A sparse curated cloud (see test_runner's FAST): the preset's path is tested, not the cloud.
        rep = run_preset("cloud", episodes[:2], None, RunConfig(poll_s=0.01, plots=False, curated_density_per_m2=200.0),
                         tmp_path, gw, world.robot, progress=False)
    sources = sorted(m[0].source.split(":")[0] for m in world.reconstructor.maps.values())
    assert sources == ["scripted", "scripted", "upload", "upload"]
    assert [r["label"] for r in rep.rows] == ["curated", "reconstructed"]
    with pytest.raises(ConfigError):
        run_preset("nope", episodes, None, RunConfig(), tmp_path, None, None)


def _with_builder(init):
    def wrapped(self, *a, **kw):
        kw.setdefault("scene_builder", lambda spec, d: box_scene())
        init(self, *a, **kw)
    return wrapped


def test_cli_options_become_the_run_config(tmp_path):
    a = build_parser().parse_args(["run", "--episodes", "e.json.gz", "--policy", "oracle", "--map-source", "curated",
                                   "--no-anticipation", "--hfov-deg", "60", "--limit", "3", "--policy-config",
                                   '{"stop_radius_m": 1.0}'])
    cfg = run_config(a)
    assert (cfg.policy, cfg.map_source, cfg.anticipation, cfg.anticipation_hfov_deg, cfg.limit) == (
        "oracle", MapSource.CURATED, False, 60.0, 3)
    assert cfg.policy_config == {"stop_radius_m": 1.0}
    assert cfg.plots and not run_config(build_parser().parse_args(["run", "--episodes", "e", "--no-plots"])).plots
    preset = build_parser().parse_args(["preset", "hfov", "--episodes", "e", "--no-plots"])
    assert not run_config(preset).plots


def test_cli_summarize_and_errors(world, gateway, episodes, tmp_path, capsys):
    from evaluation.runner import EvalRunner

    with gateway() as gw:
        EvalRunner(gw, world.robot, RunConfig(poll_s=0.01, plots=False), tmp_path / "heur",
                   progress=False).run(episodes)
    assert main(["summarize", str(tmp_path / "heur"), "--out", str(tmp_path / "all")]) == 0
    out = capsys.readouterr().out
    assert "| heur | 4 | 1 | 0 |" in out and (tmp_path / "all.csv").is_file()
    assert main(["summarize", str(tmp_path / "nothing")]) == 2
    assert main(["run", "--episodes", str(tmp_path / "missing.json.gz"), "--gateway", "http://127.0.0.1:9"]) == 2
