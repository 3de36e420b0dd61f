"""Heuristic, oracle and replay policies in a closed loop over a labelled toy world."""

from __future__ import annotations

import math

import numpy as np
import pytest
from tests.unit.planner.planner_toyworld import ToyWorld, run_episode

from shared.vln_metrics import episode_metrics, euclidean_geodesic
from services.planner.core import (
    POLICIES,
    Ablation,
    ContextError,
    ReplayConfig,
    ReplayMissError,
    ReplayPolicy,
    parse_instruction,
)
from shared.schemas import CandidateKind


def _world(**kw):
    return ToyWorld(
        landmarks={"sofa": (5.0, 0.0), "fridge": (5.0, 5.5), "bed": (-1.5, 8.0)},
        rooms={"kitchen": (3.5, 3.0, 10.0, 10.0), "living room": (-2.0, -2.0, 10.0, 2.9)},
        **kw,
    )


INSTRUCTION = "Walk straight to the sofa, then turn left into the kitchen and stop next to the fridge."


def test_instruction_parser_orders_subgoals():
    p = parse_instruction(INSTRUCTION)
    assert [sg.landmarks for sg in p.subgoals] == [["sofa"], [], ["fridge"]]
    assert p.subgoals[1].turn.value == "left" and p.subgoals[1].rooms == ["kitchen"]
    assert p.subgoals[-1].stop and p.final_landmarks == ["fridge"]
    q = parse_instruction("Turn around, go forward 4 meters past the couch, then turn slightly right and wait.")
    assert q.subgoals[0].turn.value == "around"
    assert q.subgoals[1].distance_m == pytest.approx(4.0) and q.subgoals[1].landmarks == ["sofa"]
    assert q.subgoals[2].turn.value == "slight_right" and q.subgoals[2].stop
    # "on your left" describes a landmark, it is not a turn.
    assert parse_instruction("walk past the table on your left").subgoals[0].turn is None


def test_heuristic_follows_landmarks_and_stops_at_the_final_one():
    world = _world()
    with POLICIES.create("heuristic") as policy:
        traj, stopped, decisions = run_episode(world, policy, INSTRUCTION)
    end = traj[-1]
    assert stopped, [d.reasoning for d in decisions]
    assert math.hypot(end[0] - 5.0, end[1] - 5.5) < 2.0, (traj, [d.reasoning for d in decisions])
    # It went past the sofa first (the first sub-goal), not straight at the fridge.
    assert np.min(np.hypot(traj[:, 0] - 5.0, traj[:, 1] - 0.0)) < 2.5
    m = episode_metrics(traj, (5.0, 5.5, 0.0), geodesic=euclidean_geodesic, stop_called=stopped)
    assert m.success


def test_heuristic_ignores_the_wrong_landmark_direction():
    """The same world, the instruction to the bed: the policy must head for the bed, not the fridge."""
    world = _world()
    with POLICIES.create("heuristic") as policy:
        traj, stopped, decisions = run_episode(world, policy, "Turn left and walk to the bed, stop there.")
    assert stopped and math.hypot(traj[-1][0] + 1.5, traj[-1][1] - 8.0) < 2.0, [d.reasoning for d in decisions]


def test_heuristic_without_labels_uses_turns_and_distances():
    world = _world(with_labels=False)
    with POLICIES.create("heuristic") as policy:
        instruction = "Go straight 3 meters, then turn left and walk 3 meters and stop."
        traj, stopped, _ = run_episode(world, policy, instruction)
    assert stopped
    end = traj[-1]
    # 3 m along +x (two 1.5 m moves), then left (+y) for 3 m.
    assert end[0] == pytest.approx(3.0, abs=0.8) and end[1] == pytest.approx(3.0, abs=0.8), traj


def test_heuristic_anticipation_off_still_works():
    world = _world()
    with POLICIES.create("heuristic") as policy:
        traj, stopped, _ = run_episode(world, policy, INSTRUCTION, ablation=Ablation(anticipation=False))
    assert stopped and math.hypot(traj[-1][0] - 5.0, traj[-1][1] - 5.5) < 2.5


def test_oracle_reaches_the_goal_and_follows_the_reference():
    world = _world()
    goal = (5.0, 5.0, 0.0)
    corners = np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0.0]])
    # Dense like VLN-CE's ground-truth locations (one per 0.25 m).
    legs = [np.linspace(a, b, 20, endpoint=False) for a, b in zip(corners[:-1], corners[1:])]
    reference = np.concatenate(legs + [corners[-1:]])
    with POLICIES.create("oracle") as policy:
        traj, stopped, decisions = run_episode(
            world, policy, "anything", goal=goal, geodesic=euclidean_geodesic, reference=reference
        )
    assert stopped and decisions[-1].kind == CandidateKind.STOP
    m = episode_metrics(traj, goal, geodesic=euclidean_geodesic, stop_called=True, reference_path_m=reference)
    assert m.success and m.ne_m < 1.5 and m.ndtw > 0.6
    # Following the reference (east then north), it passes near its corner rather than cutting across.
    assert np.min(np.hypot(traj[:, 0] - 5.0, traj[:, 1])) < 1.6


def test_oracle_needs_ground_truth():
    with POLICIES.create("oracle") as policy, pytest.raises(ContextError):
        run_episode(_world(), policy, "anything", max_steps=1)


def test_replay_caches_decisions_exactly(tmp_path):
    world = _world()
    path = tmp_path / "cache.jsonl"
    cfg = ReplayConfig(path=str(path), inner="heuristic")
    with POLICIES.create("replay", cfg) as policy:
        traj1, _, dec1 = run_episode(world, policy, INSTRUCTION)
        assert policy.usage.calls == len(dec1) and policy.usage.cache_hits == 0
    lines = path.read_text().splitlines()
    assert len(lines) == len(dec1)

    # Read-only: every decision must come from the cache (no inner backend is ever created).
    ro = ReplayConfig(path=str(path), inner="heuristic", mode="read_only")
    with ReplayPolicy(ro) as replay:
        traj2, _, dec2 = run_episode(world, replay, INSTRUCTION)
        assert replay._inner is None and replay.usage.cache_hits == len(dec2)
    assert np.array_equal(traj1, traj2)
    assert [d.candidate_index for d in dec1] == [d.candidate_index for d in dec2]
    assert all(d.backend.startswith("replay:") for d in dec2)
    # A different instruction is a different prompt: a miss, which read-only refuses.
    with ReplayPolicy(ro) as replay, pytest.raises(ReplayMissError):
        run_episode(world, replay, "Turn left and walk to the bed, stop there.")


def test_replay_tolerates_a_torn_last_line(tmp_path):
    path = tmp_path / "cache.jsonl"
    with POLICIES.create("replay", {"path": str(path)}) as policy:
        _, _, dec = run_episode(_world(), policy, INSTRUCTION, max_steps=3)
    with path.open("a") as f:
        f.write('{"key": "abc", "decis')  # interrupted write
    with POLICIES.create("replay", {"path": str(path)}) as policy:
        assert len(policy) == len(dec)


# --- how the heuristic reads the anticipated view (HeuristicConfig.anticipation_use) ---------------------

SOFA_WORLD = {0: "wall", 1: "sofa"}


def _view(index: int, angle_rad: float, observed: tuple[float, float], anticipated: tuple[float, float]):
    """A candidate whose observed / anticipated view show the sofa over (fraction, depth_m) of the image."""
    from services.planner.core.context import CandidateView
    from shared.schemas import Candidate

    def image(fraction: float, depth_m: float):
        labels = np.zeros((20, 20), np.int32)
        depth = np.full((20, 20), 4.0, np.float32)
        n = int(round(fraction * labels.size))
        labels.reshape(-1)[:n] = 1
        depth.reshape(-1)[:n] = depth_m
        return labels, depth

    c = Candidate(index=index, dx_m=1.5 * math.cos(angle_rad), dy_m=1.5 * math.sin(angle_rad),
                  angle_rad=angle_rad, distance_m=1.5)
    ol, od = image(*observed)
    al, ad = image(*anticipated)
    return CandidateView(candidate=c, observed_labels=ol, observed_depth_m=od, anticipated_labels=al,
                         anticipated_depth_m=ad, anticipated_hole_fraction=0.0)


def _choose(use: str, views) -> int:
    from services.planner.core import StepContext
    from shared.schemas import Pose

    ctx = StepContext(instruction="Walk to the sofa and stop there.", step=1,
                      pose=Pose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0), candidates=views,
                      label_names=SOFA_WORLD)
    with POLICIES.create("heuristic", {"anticipation_use": use}) as policy:
        policy.reset("m")
        return policy.decide(ctx).candidate_index


def test_heuristic_combine_keeps_what_the_agent_sees():
    """The sofa fills 30 % of the view towards candidate 0, whose anticipated view (past it) does not show
    it; candidate 1's anticipated view shows a sliver far away. Replacing the observed view by the
    anticipated one walks away from the sofa; combining them does not."""
    views = [_view(0, 0.4, observed=(0.30, 3.0), anticipated=(0.0, 4.0)),
             _view(1, -0.4, observed=(0.0, 4.0), anticipated=(0.05, 5.0))]
    assert _choose("replace", views) == 1
    assert _choose("combine", views) == 0


def test_heuristic_combine_prefers_the_candidate_that_reaches_the_target():
    """Both candidates see the sofa alike from here; from candidate 1 it is within reach (1 m), from
    candidate 0 still 5 m away: anticipation tells them apart."""
    views = [_view(0, 0.4, observed=(0.10, 4.0), anticipated=(0.10, 5.0)),
             _view(1, -0.4, observed=(0.10, 4.0), anticipated=(0.10, 1.0))]
    assert _choose("combine", views) == 1
