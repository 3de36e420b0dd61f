"""The VLN-CE prediction file and the per-episode plots of a run (through the real runner and gateway)."""

from __future__ import annotations

import csv
import json
import math
import re
import shutil

import numpy as np
import pytest
from PIL import Image

from evaluation.plots import backtrack_segments, plot_name
from evaluation.predictions import episode_states, habitat_heading
from evaluation.results import EpisodeResult
from evaluation.runner import EvalRunner, RunConfig
from shared.bus import FakeNetwork
from tests.unit.evaluation.conftest import World, gateway_client, make_episode


def vlnce_heading_of_quaternion(q_xyzw) -> float:
    """VLN-CE's VLNCEInferenceEnv.get_info heading, written out independently: rotate (0, 0, -1) by the
    inverse rotation and take the polar angle of (-v_z, v_x)."""
    x, y, z, w = q_xyzw
    qi = np.array([-x, -y, -z, w])  # inverse of a unit quaternion

    def rotate(q, v):
        u, s = q[:3], q[3]
        return 2 * np.dot(u, v) * u + (s * s - np.dot(u, u)) * v + 2 * s * np.cross(u, v)

    hv = rotate(qi, np.array([0.0, 0.0, -1.0]))
    return math.atan2(hv[0], -hv[2])


@pytest.mark.parametrize("world_heading", [0.0, 0.7, math.pi / 2, -2.5, math.pi])
def test_heading_matches_vlnce_convention(world_heading):
    from shared.geometry import heading_to_habitat_quaternion

    want = vlnce_heading_of_quaternion(heading_to_habitat_quaternion(world_heading))
    assert math.isclose(math.cos(habitat_heading(world_heading)), math.cos(want), abs_tol=1e-9)
    assert math.isclose(math.sin(habitat_heading(world_heading)), math.sin(want), abs_tol=1e-9)


def test_states_are_habitat_frame_with_the_stop_last():
    traj = np.array([[0.0, 0.0, 0.1], [1.0, 0.0, 0.1], [1.0, 0.0, 0.1], [1.0, 2.0, 0.1]])
    states = episode_states(traj, start_heading_rad=math.pi, stop_called=True)
    assert [s["stop"] for s in states] == [False, False, False, True]
    # world (x, y, z) = habitat (x, -z, y)
    assert states[3]["position"] == pytest.approx([1.0, 0.1, -2.0])
    assert states[0]["heading"] == pytest.approx(habitat_heading(math.pi))
    assert states[1]["heading"] == pytest.approx(habitat_heading(0.0))
    assert states[2]["heading"] == states[1]["heading"]  # a blocked move keeps the heading
    assert states[3]["heading"] == pytest.approx(habitat_heading(math.pi / 2))
    assert not episode_states(traj, None, stop_called=False)[-1]["stop"]


def test_backtrack_segments_follow_the_decisions():
    r = EpisodeResult(episode_id="1", scene_id="s", status="done", trajectory_m=[[0, 0, 0], [1, 0, 0], [0, 0, 0]],
                      decisions=[{"step": 0, "kind": "waypoint"}, {"step": 1, "kind": "backtrack"},
                                 {"step": 2, "kind": "stop"}])
    assert backtrack_segments(r) == [1]
    assert plot_name("a/b c") == "a_b_c.png"


EPISODES = [make_episode(1, "generated:1", goal=(4.0, 0.0, 0.0)),
            make_episode(2, "generated:1", start=(1.0, 1.0, 0.0), goal=(1.0, 8.0, 0.0)),
            make_episode(3, "mp3d/NOPE/NOPE.glb", goal=(3.0, 0.0, 0.0))]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same episodes run with plots on (``runs[True]``) and off (``runs[False]``) through one scripted
    world: made once for the module, since its tests only read what the runs wrote (and resume copies)."""
    root = tmp_path_factory.mktemp("plots")
    world = World(FakeNetwork())
    try:
        with gateway_client(world, root / "gw.sqlite3") as gw:
            return {plots: EvalRunner(gw, world.robot, RunConfig(max_steps=5, poll_s=0.02, plots=plots),
                                      root / ("on" if plots else "off"), progress=False).run(EPISODES)
                    for plots in (True, False)}
    finally:
        world.close()


def test_a_run_writes_the_prediction_file_and_linked_plots(runs):
    episodes, report = EPISODES, runs[True]
    out = report.out_dir
    by_id = {r.episode_id: r for r in report.results}

    preds = json.loads((out / "predictions.json").read_text())
    assert sorted(preds) == ["1", "2"]  # episode 3's scene is missing: it has no trajectory
    for eid, states in preds.items():
        r, e = by_id[eid], episodes[int(eid) - 1]
        assert set(states[0]) == {"position", "heading", "stop"}
        assert len(states) == len(r.trajectory_m)
        # positions are Habitat's frame: the episode's own start_position comes back for the first state
        assert states[0]["position"] == pytest.approx(e.raw["start_position"], abs=1e-5)
        assert states[0]["heading"] == pytest.approx(vlnce_heading_of_quaternion(e.raw["start_rotation"]), abs=1e-5)
        # the path length over the file's positions is the run's TL, and the final stop is the run's
        hab = np.array([s["position"] for s in states])
        assert np.linalg.norm(np.diff(hab, axis=0), axis=1).sum() == pytest.approx(r.metrics["tl_m"], abs=1e-4)
        assert states[-1]["stop"] is r.metrics["stop_called"] and not any(s["stop"] for s in states[:-1])
    assert preds["1"][-1]["stop"] and not preds["2"][-1]["stop"]  # 2 ran out of steps

    md = (out / "summary.md").read_text()
    links = re.findall(r"\]\((plots/[^)]+\.png)\)", md)
    assert sorted(links) == ["plots/1.png", "plots/2.png"] and "predictions.json" in md
    for rel in links:
        img = Image.open(out / rel)
        assert img.size[0] >= 600 and img.size[1] >= 600
        px = np.asarray(img.convert("RGB")).reshape(-1, 3).astype(np.uint32)
        # Colours packed into one integer each: np.unique(px, axis=0) counts the same, 0.43 s vs 0.006 s a plot.
        assert len(np.unique(px[:, 0] << 16 | px[:, 1] << 8 | px[:, 2])) > 20  # a drawn picture, not a blank canvas


def _episode_rows(md: str) -> list[str]:
    """The rows of summary.md's episodes table, each plot link read as ``-``."""
    return [re.sub(r"\[[^]]*\]\(plots/[^)]*\)", "-", line) for line in md.splitlines()
            if re.match(r"\| \d+ \|", line)]


class NoGateway:
    def __getattr__(self, name):
        raise AssertionError(f"the gateway was called ({name}) by a run that had nothing left to run")


def test_plots_off_draws_no_picture_and_changes_no_number(runs, tmp_path):
    on, off = runs[True], runs[False]
    assert sorted(p.name for p in on.out_dir.rglob("*.png")) == ["1.png", "2.png"]
    assert not list(off.out_dir.rglob("*.png"))

    def outcome(r):
        return (r.episode_id, r.status, r.reason, r.seed, r.metrics, r.trajectory_m, r.prompt_tokens, r.cost_usd,
                [d["reasoning"] for d in r.decisions], r.ledger)

    assert [outcome(r) for r in off.results] == [outcome(r) for r in on.results]
    # Every number of the summary but the measured step latency (step_s), in both tables.
    assert {k: v for k, v in off.row.items() if k != "step_s"} == {k: v for k, v in on.row.items() if k != "step_s"}
    on_md, off_md = (r.tables[0].read_text() for r in (on, off))
    on_csv, off_csv = ([{k: v for k, v in row.items() if k != "step_s"} for row in csv.DictReader(r.tables[1].open())]
                       for r in (on, off))
    assert off_csv == on_csv and len(on_csv) == 1
    assert (json.loads((off.out_dir / "predictions.json").read_text())
            == json.loads((on.out_dir / "predictions.json").read_text()))
    # summary.md lists the same episodes (3 skipped, 1 and 2 run) with the same numbers, says the plots were
    # off and links none.
    assert _episode_rows(off_md) == _episode_rows(on_md) and len(_episode_rows(off_md)) == 3
    assert "Plots off" in off_md and "plots/" not in off_md and "Plots off" not in on_md
    assert "[predictions.json](predictions.json) (2 episodes" in off_md

    # Not a setting of the experiment: a resumed run may switch plots either way (nothing is left to run, so
    # it only rewrites its outputs; episode 3's scene is still missing).
    for src, plots in ((off, True), (on, False)):
        out = tmp_path / f"resumed-{plots}"
        shutil.copytree(src.out_dir, out)
        again = EvalRunner(NoGateway(), None, RunConfig(max_steps=5, plots=plots), out, progress=False).run(EPISODES)
        assert again.resumed == 2 and [outcome(r) for r in again.results[:2]] == [outcome(r) for r in on.results[:2]]
        md = (out / "summary.md").read_text()
        assert sorted(re.findall(r"\]\((plots/[^)]+)\)", md)) == (["plots/1.png", "plots/2.png"] if plots else [])
        assert ("Plots off" in md) is not plots and _episode_rows(md) == _episode_rows(on_md)
        assert sorted(p.name for p in out.rglob("*.png")) == ["1.png", "2.png"]  # old ones stay, unlinked


def test_a_recorded_run_keeps_each_missions_rrd_and_links_it(world, gateway, tmp_path):
    import rerun as rr

    out = tmp_path / "run"
    episodes = [make_episode(1, "generated:1", goal=(3.0, 0.0, 0.0))]
    with gateway() as gw:
        report = EvalRunner(gw, world.robot, RunConfig(max_steps=5, poll_s=0.02, record=True, plots=False), out,
                            progress=False).run(episodes)
    (r,) = report.results
    assert world.planner.requests[-1].options.record is True
    assert r.recording == "recordings/1.rrd"
    entities = {c.entity_path.lstrip("/") for c in rr.chunk.RrdReader(str(out / r.recording)).stream()}
    assert {"world/map", "world/goal", "events"} <= entities
    assert "[1.rrd](recordings/1.rrd)" in (out / "summary.md").read_text()
