"""The VLN-CE prediction file and the per-episode plots of a run (through the real runner and gateway)."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from PIL import Image

from evaluation.plots import backtrack_segments, plot_name
from evaluation.predictions import episode_states, habitat_heading
from evaluation.results import EpisodeResult
from evaluation.runner import EvalRunner, RunConfig
from tests.unit.evaluation.conftest import make_episode


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


def test_a_run_writes_the_prediction_file_and_linked_plots(world, gateway, tmp_path):
    episodes = [make_episode(1, "generated:1", goal=(4.0, 0.0, 0.0)),
                make_episode(2, "generated:1", start=(1.0, 1.0, 0.0), goal=(1.0, 8.0, 0.0)),
                make_episode(3, "mp3d/NOPE/NOPE.glb", goal=(3.0, 0.0, 0.0))]
    out = tmp_path / "run"
    with gateway() as gw:
        report = EvalRunner(gw, world.robot, RunConfig(max_steps=5, poll_s=0.02), out, progress=False).run(episodes)
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
        px = np.asarray(img.convert("RGB")).reshape(-1, 3)
        assert len(np.unique(px, axis=0)) > 20  # a drawn picture, not a blank canvas


def test_a_recorded_run_keeps_each_missions_rrd_and_links_it(world, gateway, tmp_path):
    import rerun as rr

    out = tmp_path / "run"
    episodes = [make_episode(1, "generated:1", goal=(3.0, 0.0, 0.0))]
    with gateway() as gw:
        report = EvalRunner(gw, world.robot, RunConfig(max_steps=5, poll_s=0.02, record=True), out,
                            progress=False).run(episodes)
    (r,) = report.results
    assert world.planner.requests[-1].options.record is True
    assert r.recording == "recordings/1.rrd"
    entities = {c.entity_path.lstrip("/") for c in rr.chunk.RrdReader(str(out / r.recording)).stream()}
    assert {"world/map", "world/goal", "events"} <= entities
    assert "[1.rrd](recordings/1.rrd)" in (out / "summary.md").read_text()
