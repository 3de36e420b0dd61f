"""Several robots at once: the runner shards whole scenes over robots (each its own gateway and scripted
services) and runs them concurrently; the per-episode results do not depend on the number of robots."""

from __future__ import annotations

from contextlib import ExitStack, contextmanager

from evaluation.runner import EvalRunner, Lane, RunConfig, group_by_scene, shard_scenes
from shared.bus import FakeNetwork
from tests.unit.evaluation.conftest import World, box_scene, gateway_client, make_episode

SCENES = ["generated:1", "generated:2", "generated:3"]


def _episodes():
    # Interleaved as in a real file; scene 1 has the most episodes.
    goals = [(4.0, 0.0, 0.0), (0.0, 3.0, 0.0), (2.0, 2.0, 0.0), (5.0, 1.0, 0.0), (1.0, 4.0, 0.0), (3.0, 0.0, 0.0),
             (0.0, 6.0, 0.0)]
    scenes = [SCENES[0], SCENES[1], SCENES[2], SCENES[0], SCENES[1], SCENES[0], SCENES[2]]
    return [make_episode(i + 1, s, goal=g) for i, (s, g) in enumerate(zip(scenes, goals))]


@contextmanager
def fleet(n, tmp_path):
    """``n`` robots, each a scripted world and a real gateway app of its own."""
    with ExitStack() as stack:
        worlds, lanes = [], []
        for k in range(n):
            world = World(FakeNetwork())
            stack.callback(world.close)
            gateway = stack.enter_context(gateway_client(world, tmp_path / f"gw{k}-{n}.sqlite3", f"gw-{k}"))
            worlds.append(world)
            lanes.append(Lane(gateway, world.robot))
        yield worlds, lanes


def _run(n, tmp_path, **cfg):
    with fleet(n, tmp_path) as (worlds, lanes):
        runner = EvalRunner(lanes[0].gateway, lanes[0].scenes, RunConfig(poll_s=0.01, max_steps=8, plots=False, **cfg),
                            tmp_path / f"out{n}", progress=False, scene_builder=lambda spec, d: box_scene(),
                            lanes=lanes[1:])
        report = runner.run(_episodes())
        return report, [w.robot_io.loaded for w in worlds], [len(w.planner.requests) for w in worlds]


def test_shards_keep_scenes_whole_and_balance_episodes():
    groups = group_by_scene(_episodes())
    assert shard_scenes(groups, 1) == [SCENES]
    assert shard_scenes(groups, 3) == [[SCENES[0]], [SCENES[1]], [SCENES[2]]]
    assert shard_scenes(groups, 2) == [[SCENES[0]], [SCENES[1], SCENES[2]]]  # 3 episodes vs 2 + 2
    assert shard_scenes(groups, 5)[3:] == [[], []]


def test_three_robots_give_the_results_of_one(tmp_path):
    one, loaded1, _ = _run(1, tmp_path)
    three, loaded3, missions3 = _run(3, tmp_path)
    assert loaded1 == [SCENES]
    # Each robot loaded its one scene once and ran only that scene's episodes.
    assert loaded3 == [[SCENES[0]], [SCENES[1]], [SCENES[2]]] and missions3 == [3, 2, 2]
    assert [r.episode_id for r in one.results] == [r.episode_id for r in three.results] == [str(i) for i in range(1, 8)]
    for a, b in zip(one.results, three.results):
        assert (a.status, a.metrics, a.trajectory_m, a.seed) == (b.status, b.metrics, b.trajectory_m, b.seed)
        assert [d["reasoning"] for d in a.decisions] == [d["reasoning"] for d in b.decisions]
        assert len(a.ledger) == len(b.ledger) and a.prompt_tokens == b.prompt_tokens
    keep = ("count", "SR", "SPL", "NE", "nDTW", "prompt_tokens", "cost_usd")
    assert {k: one.row[k] for k in keep} == {k: three.row[k] for k in keep}


def test_a_budget_stops_every_robot(tmp_path):
    # Every episode costs at least $0.001 (>= 2 steps x $0.0005): the first results cross it, so no robot
    # starts a second episode; the ones already running finish and are kept.
    report, _, missions = _run(3, tmp_path, budget_usd=0.001)
    assert report.stopped and "were not started" in report.stopped
    assert report.ran == sum(missions) and all(m <= 1 for m in missions)
    assert report.row["count"] == report.ran


def test_a_budget_reached_mid_episode_cancels_the_missions_of_every_robot(tmp_path):
    with fleet(3, tmp_path) as (worlds, lanes):
        for w in worlds:
            w.planner.interval_s = 0.1  # three robots walk at once, a step each 0.1 s
        runner = EvalRunner(lanes[0].gateway, lanes[0].scenes,
                            RunConfig(poll_s=0.01, max_steps=8, budget_tokens=400, plots=False), tmp_path / "out",
                            progress=False, scene_builder=lambda spec, d: box_scene(), lanes=lanes[1:])
        report = runner.run(_episodes())
        missions = [len(w.planner.requests) for w in worlds]
    # 110 tokens per step: the budget is reached at about the fourth step of the three robots together,
    # before any episode (3 to 6 steps) could end; every mission running then is cancelled.
    assert {r.status for r in report.results} <= {"stopped", "done"} and report.row["errors"] == 0
    assert report.row["stopped"] >= 2 and report.ran == sum(missions) and all(m <= 1 for m in missions)
    # Overshoot: at most the steps in flight when the budget was seen (one or two per robot).
    assert 440 <= report.spent.tokens <= 400 + 3 * 2 * 110
    assert "were not started" in report.stopped
