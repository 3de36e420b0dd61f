"""The runner on the real system: launcher, gateway, robot-io scene switching, curated map, oracle policy."""

from __future__ import annotations

import json

import pytest

from evaluation.cli import main
from evaluation.dataset import SetSpec, generate_set, write_set
from evaluation.results import ResultsLog

pytestmark = [pytest.mark.e2e, pytest.mark.system]


# A small house: the runner's path (scene switch, curated map, missions, resume) does not depend on its size,
# and generating it, building its curated cloud and indexing it cost less than half of the default house's.
AREA_M2 = 60.0
# robot-io starts in another small house, so the runner's scene switch is a real one; robot-io's default
# house would cost two nav-grid builds (the run and the resume each start the system) for nothing.
START_SCENE = "generated:3:area=50"
# A sparse curated cloud (a tenth of the runner's default 1000 per m2): the oracle follows the ground truth,
# and what this test proves (scene switch, curated map, missions, resume) does not depend on the map's
# density; building, uploading and indexing the default one was most of the run's CPU.
CURATED_DENSITY_PER_M2 = "100"


def test_make_eval_path_on_a_generated_house(tmp_path, capsys, monkeypatch, system_on_scene):
    monkeypatch.setenv("ANT_ROBOT_CONFIG", json.dumps({"scene": START_SCENE}))
    ds, gt = generate_set(SetSpec(houses=1, per_house=2, floors=(1,), seed=7, area_m2=AREA_M2), with_gt=True)
    assert all(e.scene_id != START_SCENE for e in ds.episodes)
    episodes = write_set(ds, gt, tmp_path / "set.json.gz")[0]
    out = tmp_path / "out"
    # 15 steps: the oracle reaches the nearer goal in 9; the other episode may use them all (it did use 25).
    argv = ["run", "--episodes", str(episodes), "--out", str(out), "--policy", "oracle", "--map-source", "curated",
            "--max-steps", "15", "--mission-timeout-s", "240", "--no-progress",
            "--curated-density-per-m2", CURATED_DENSITY_PER_M2]
    assert main(argv) == 0
    results = ResultsLog(out / "results.jsonl").load()
    assert sorted(results) == ["1", "2"]
    for r in results.values():
        assert r.status == "done", r.reason
        assert r.metrics["shortest_m"] == pytest.approx(ds.by_id()[int(r.episode_id)].geodesic_distance_m, rel=0.05)
        assert len(r.trajectory_m) >= 2 and r.step_latency_s
    # The oracle follows the ground truth: it must reach the goal on these easy episodes.
    assert sum(r.metrics["success"] for r in results.values()) >= 1
    assert "| oracle/curated | 2 | 0 | 0 |" in capsys.readouterr().out
    # Resuming does nothing (everything is done) and prints the same table; it runs against the session's
    # launched system (tests/conftest.py) through ``--gateway``, the other way the runner finds a system,
    # rather than starting a second one of its own only to find nothing left to do.
    assert main([*argv, "--gateway", system_on_scene.gateway_url]) == 0
    assert "0 episodes run, 2 resumed" in capsys.readouterr().out
