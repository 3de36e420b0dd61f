"""The runner against a real gateway app and scripted services: grouping, maps, resume, skips, errors."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tests.unit.evaluation.conftest import box_scene, make_episode
from evaluation.errors import ConfigError, SceneSwitchError
from shared.vln_metrics import episode_metrics, euclidean_geodesic
from evaluation.results import ResultsLog
from evaluation.runner import EvalRunner, SceneMapIndex, MapSource, RunConfig, episode_seed, group_by_scene, map_id_for
from libs.world import GroundTruth

# Plots off: no test here looks at them (test_predictions_plots does), and they cost ~0.1 s of CPU each.
# Curated clouds at 200 points per m2 (11.8k points for the box room, not 59k): the tests check the runner's
# path (upload, map index, reuse), not the cloud, and sampling one costs 0.05 s instead of 0.19 s.
FAST = {"poll_s": 0.01, "plots": False, "curated_density_per_m2": 200.0}


def runner(gw, world, out, **cfg):
    return EvalRunner(gw, world.robot, RunConfig(**{**FAST, **cfg}), out, progress=False,
                      scene_builder=lambda spec, d: box_scene())


def test_group_by_scene_keeps_first_appearance_and_file_order(episodes):
    groups = group_by_scene(episodes)
    assert list(groups) == ["generated:1", "generated:2:floors=2", "mp3d/NOPE/NOPE.glb"]
    assert [e.episode_id for e in groups["generated:1"]] == [1, 4]
    assert [e.episode_id for e in groups["generated:2:floors=2"]] == [2, 5]


def test_map_ids_are_gateway_safe_and_distinct():
    pattern = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    scenes = ["generated:1", "generated:1:floors=2", "mp3d/2azQ1b91cZZ/2azQ1b91cZZ.glb", "x" * 300,
              "/abs/path/with spaces/scene.glb"]
    ids = {map_id_for(s, src) for s in scenes for src in MapSource}
    assert len(ids) == 2 * len(scenes)
    assert all(pattern.match(i) for i in ids)
    assert map_id_for("generated:1", "curated") == map_id_for("generated:1", MapSource.CURATED)


def test_episode_seed_is_stable_and_distinct():
    seeds = [episode_seed(0, i) for i in range(200)]
    assert len(set(seeds)) == 200 and seeds == [episode_seed(0, i) for i in range(200)]
    assert episode_seed(1, 5) != episode_seed(0, 5)


def test_full_run(world, gateway, episodes, tmp_path):
    with gateway() as gw:
        report = runner(gw, world, tmp_path / "out", max_steps=5).run(episodes)
    by_id = {r.episode_id: r for r in report.results}
    assert list(by_id) == ["1", "2", "3", "4", "5"]
    # Grouped by scene: each scene loaded once, in order; the missing one skipped with its reason.
    assert world.robot_io.loaded == ["generated:1", "generated:2:floors=2"]
    assert by_id["3"].status == "skipped" and "mp3d/NOPE/NOPE.glb" in by_id["3"].reason
    # The missions got each episode's start, goal, reference path and derived seed.
    reqs = {r.instruction: r for r in world.planner.requests}
    assert len(world.planner.requests) == 4
    for e in episodes:
        if e.episode_id == 3:
            continue
        opts = next(r.options for r in world.planner.requests
                    if r.options.goal_m == pytest.approx(tuple(e.goal_m)) and r.options.seed == episode_seed(0, e.episode_id))
        assert opts.start_pose.position_m == pytest.approx(e.start_pose.position_m)
        assert np.allclose(opts.reference_path_m, e.reference_path_m)
        assert opts.max_steps == 5 and opts.policy == "heuristic"
    assert set(reqs) == {"walk ahead"}
    # Episode 4 is 7 m away at 1 m per step: the budget of 5 steps ends it without a stop.
    assert by_id["4"].status == "done" and by_id["4"].metrics["stop_called"] is False
    # Metrics agree with an independent computation over the recorded trajectory.
    for eid in ("1", "2", "4", "5"):
        r, e = by_id[eid], next(x for x in episodes if str(x.episode_id) == eid)
        ref = episode_metrics(np.array(r.trajectory_m), e.goal_m, geodesic=euclidean_geodesic,
                              stop_called=r.metrics["stop_called"], reference_path_m=e.reference_path_m)
        assert r.metrics == pytest.approx(ref.to_dict())
        assert r.step_latency_s and r.prompt_tokens == 100 * len(r.step_latency_s) and r.decisions
    assert report.row["count"] == 4 and report.row["skipped"] == 1 and report.row["SR"] == 75.0
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "| 75.0 |" in md and "NOPE.glb" in md
    assert (tmp_path / "out" / "summary.csv").read_text().startswith("label,count,skipped,errors,stopped,NE")


def test_resume_skips_finished_episodes(world, gateway, episodes, tmp_path):
    out = tmp_path / "out"
    with gateway() as gw:
        first = runner(gw, world, out, limit=2).run(episodes)
        assert first.ran == 2 and len(world.planner.requests) == 2
        second = runner(gw, world, out).run(episodes)
    assert second.resumed == 2 and second.ran == 3
    assert len(world.planner.requests) == 4  # episodes 1 and 2 were not run again
    lines = (out / "results.jsonl").read_text().splitlines()
    assert [json.loads(x)["episode_id"] for x in lines] == ["1", "2", "3", "4", "5"]  # pending grouped by first appearance


def test_interrupted_run_resumes_without_redoing(world, gateway, episodes, tmp_path, monkeypatch):
    out = tmp_path / "out"
    with gateway() as gw:
        r = runner(gw, world, out)
        real = r.run_episode
        calls = []

        def flaky(*a, **kw):
            if len(calls) == 2:
                raise KeyboardInterrupt
            calls.append(1)
            return real(*a, **kw)

        monkeypatch.setattr(r, "run_episode", flaky)
        with pytest.raises(KeyboardInterrupt):
            r.run(episodes)
        assert list(ResultsLog(out / "results.jsonl").load()) == ["1", "4"]
        again = runner(gw, world, out).run(episodes)
    assert again.resumed == 2 and again.row["count"] == 4
    assert len(world.planner.requests) == 4


def test_errors_are_recorded_and_retried_on_resume(world, gateway, tmp_path):
    eps = [make_episode(1, "generated:1"), make_episode(2, "generated:1", text="crash now"),
           make_episode(3, "generated:1", text="hang here")]
    out = tmp_path / "out"
    with gateway() as gw:
        rep = runner(gw, world, out, mission_timeout_s=0.5).run(eps)
        by_id = {r.episode_id: r for r in rep.results}
        assert by_id["1"].status == "done"
        assert by_id["2"].status == "error" and "scripted crash" in by_id["2"].reason
        assert by_id["3"].status == "error" and by_id["3"].reason.startswith("timeout")
        assert rep.row["errors"] == 2 and rep.row["count"] == 1
        state = gw.mission(by_id["3"].mission_id)["state"]
        assert state == "cancelled"
        n = len(world.planner.requests)
        runner(gw, world, out, mission_timeout_s=0.5, retry_errors=False).run(eps)
        assert len(world.planner.requests) == n
        # Both errors run again. What they end in does not matter here, so the hang times out at once.
        runner(gw, world, out, mission_timeout_s=0.05).run(eps)
        assert len(world.planner.requests) == n + 2


def test_maps_are_built_once_per_scene_and_source_and_reused(world, gateway, episodes, tmp_path):
    cache = SceneMapIndex(tmp_path / "maps.json")
    with gateway() as gw:
        for source, out in (("reconstructed", "a"), ("curated", "b"), ("curated", "c")):
            EvalRunner(gw, world.robot, RunConfig(map_source=source, **FAST), tmp_path / out, map_cache=cache,
                       progress=False, scene_builder=lambda spec, d: box_scene()).run(episodes)
    maps = world.reconstructor.maps
    assert len(maps) == 4  # 2 scenes x 2 sources; run "c" reused "b"'s uploads
    cur = maps[cache.get("generated:1", "curated")][0]
    assert cur.version == 1 and cur.source.startswith("upload:") and cur.point_count > 5000
    assert json.loads((tmp_path / "maps.json").read_text())["reconstructed|generated:1"].startswith("eval-reconstructed")
    used = {r.map_id for r in ResultsLog(tmp_path / "c" / "results.jsonl").load().values() if r.map_id}
    assert used == {cache.get("generated:1", "curated"), cache.get("generated:2:floors=2", "curated")}


def test_a_scene_robot_io_cannot_load_is_skipped(world, gateway, tmp_path):
    eps = [make_episode(1, "generated:7:broken"), make_episode(2, "generated:1")]
    with gateway() as gw:
        rep = runner(gw, world, tmp_path / "o").run(eps)
    assert [r.status for r in rep.results] == ["skipped", "done"]
    assert "could not be loaded" in rep.results[0].reason


def test_ground_truth_is_the_ndtw_reference(world, gateway, tmp_path):
    e = make_episode(1, "generated:1", goal=(4.0, 0.0, 0.0))
    dense = np.column_stack([np.linspace(0, 4, 17), np.zeros(17), np.zeros(17)])
    gt = {"1": GroundTruth.from_world(dense, [1] * 16 + [0])}
    with gateway() as gw:
        runner(gw, world, tmp_path / "o").run([e], gt)
        with pytest.raises(ConfigError, match="ground-truth"):
            runner(gw, world, tmp_path / "p", reference="gt").run([e])
    assert np.allclose(world.planner.requests[0].options.reference_path_m, dense)


def test_resuming_with_other_settings_is_refused(world, gateway, episodes, tmp_path):
    with gateway() as gw:
        runner(gw, world, tmp_path / "o", limit=1).run(episodes)
        runner(gw, world, tmp_path / "o", limit=2).run(episodes)  # limit does not define the experiment
        with pytest.raises(ConfigError, match="policy"):
            runner(gw, world, tmp_path / "o", policy="oracle").run(episodes)


def test_several_scenes_need_a_scene_switcher(gateway, episodes, tmp_path):
    with gateway() as gw:
        r = EvalRunner(gw, None, RunConfig(**FAST), tmp_path / "o", progress=False)
        with pytest.raises(SceneSwitchError):
            r.run(episodes)


def test_missing_scenes_of_real_r2r_ce_are_skipped_without_calls(shared_data, tmp_path):
    from libs.world import read_episodes

    ds = read_episodes(shared_data / "r2r_ce" / "R2R_VLNCE_v1-3_preprocessed_val_unseen.json.gz")

    class NoGateway:
        def __getattr__(self, name):
            raise AssertionError(f"the gateway was called ({name}) for a missing scene")

    rep = EvalRunner(NoGateway(), None, RunConfig(limit=8), tmp_path / "o", progress=False,
                     ).run(ds.episodes) if len(group_by_scene(ds.episodes[:8])) == 1 else None
    if rep is None:  # several scenes: give a switcher that must not be called either
        rep = EvalRunner(NoGateway(), NoGateway(), RunConfig(limit=8, scenes_dir=tmp_path), tmp_path / "o",
                         progress=False).run(ds.episodes)
    assert [r.status for r in rep.results] == ["skipped"] * 8
    assert all(r.scene_id.endswith(".glb") and r.scene_id in r.reason for r in rep.results)
    assert rep.row["count"] == 0 and rep.row["skipped"] == 8
