"""Oracle robustness (no oscillation, stop inside the success radius) and heuristic sub-goal progress."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.planner.core import POLICIES, parse_instruction
from services.planner.core.context import OracleInfo, StepContext, build_candidate_views, with_stop_and_backtrack
from shared.schemas import Candidate, CandidateKind, Pose


def _ctx(pos, offsets, trajectory, goal, geodesic, step=3, max_steps=30, reference=None, previous=None):
    pose = Pose(position_m=pos, heading_rad=0.0)
    cands = [Candidate(index=i, dx_m=dx, dy_m=dy, angle_rad=math.atan2(dy, dx), distance_m=math.hypot(dx, dy))
             for i, (dx, dy) in enumerate(offsets)]
    cands = with_stop_and_backtrack(cands, pose, previous)
    return StepContext(instruction="go", step=step, pose=pose, candidates=build_candidate_views(cands, None, None),
                       trajectory_m=np.asarray(trajectory, float), max_steps=max_steps,
                       oracle=OracleInfo(goal_m=np.asarray(goal, float), reference_path_m=reference,
                                         geodesic=geodesic))


def _euclid(a, b):
    return float(np.linalg.norm(np.asarray(a)[:2] - np.asarray(b)[:2]))


def test_oracle_does_not_return_to_where_it_stood():
    # The goal is behind a wall: going back to the previous node looks (slightly) closer by the
    # geodesic, which made the oracle oscillate. The tabu prefers the unvisited way round.
    here, before = (0.0, 0.0, 0.0), (-1.0, 0.0, 0.0)

    def geo(a, b):
        return _euclid(a, b) + (1.5 if a[1] > 0.5 and a[0] > -0.5 else 0.0)

    ctx = _ctx(here, [(-1.0, 0.0), (0.0, 1.0)], [before, here], (-1.0, 6.0, 0.0), geo)
    with POLICIES.create("oracle") as policy:
        d = policy.decide(ctx)
    chosen = ctx.candidate(d.candidate_index)
    assert chosen.kind == CandidateKind.WAYPOINT and chosen.candidate.dy_m == pytest.approx(1.0), d.reasoning
    # Without the history the way back is taken (the tabu, not the geometry, made the difference).
    ctx2 = _ctx(here, [(-1.0, 0.0), (0.0, 1.0)], [here], (-1.0, 6.0, 0.0), geo)
    with POLICIES.create("oracle") as policy:
        d2 = policy.decide(ctx2)
    assert ctx2.candidate(d2.candidate_index).candidate.dx_m == pytest.approx(-1.0)


def test_oracle_stops_inside_the_success_radius_when_nothing_gets_closer():
    here = (0.0, 0.0, 0.0)
    ctx = _ctx(here, [(0.0, 1.0), (-1.5, 0.0)], [here], (2.2, 0.0, 0.0), _euclid)
    with POLICIES.create("oracle") as policy:
        d = policy.decide(ctx)
    assert ctx.candidate(d.candidate_index).kind == CandidateKind.STOP, d.reasoning
    # Farther than the radius less its margin it keeps going.
    ctx = _ctx(here, [(1.0, 0.0), (-1.5, 0.0)], [here], (2.8, 0.0, 0.0), _euclid)
    with POLICIES.create("oracle") as policy:
        d = policy.decide(ctx)
    assert ctx.candidate(d.candidate_index).kind == CandidateKind.WAYPOINT


def test_oracle_stops_on_the_last_step_inside_the_radius():
    here = (0.0, 0.0, 0.0)
    ctx = _ctx(here, [(1.5, 0.0)], [here], (2.4, 0.0, 0.0), _euclid, step=29, max_steps=30)
    with POLICIES.create("oracle") as policy:
        d = policy.decide(ctx)
    assert ctx.candidate(d.candidate_index).kind == CandidateKind.STOP


def test_leave_clauses_are_parsed():
    p = parse_instruction("Exit the kitchen. Turn left and go through the hallway. Stop next to the bed in the bedroom.")
    assert p.subgoals[0].leave and p.subgoals[0].rooms == ["kitchen"] and "kitchen" not in p.subgoals[0].targets
    assert not any(sg.leave for sg in p.subgoals[1:])
    assert p.subgoals[-1].stop and not p.subgoals[-1].leave
