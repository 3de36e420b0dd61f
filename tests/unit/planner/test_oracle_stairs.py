"""The oracle on stairs: a candidate's end point is found on the floor it really leads to.

The fake world is one flight of stairs (rise 0.7 per metre of run, y from 0 to 4) between two floors, with a
geodesic that snaps points like the simulator's nav grid: within 0.5 m of the surface a point is on it,
otherwise it snaps to the nearest surface point with height weighted 4x and pays the plan offset.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.planner.core import POLICIES
from services.planner.core.context import OracleInfo, StepContext, build_candidate_views, with_stop_and_backtrack
from services.planner.core.oracle import OracleConfig, end_heights
from shared.schemas import Candidate, CandidateKind, Pose

SLOPE, TOP = 0.7, 2.8
YS = np.linspace(-3.0, 9.0, 1201)  # nodes along the corridor, 1 cm apart


def surface_z(y):
    return np.clip(SLOPE * np.asarray(y, float), 0.0, TOP)


ZS = surface_z(YS)
ARC = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(YS), np.diff(ZS)))])  # 3-D walking length


def _snap(p) -> tuple[int, float]:
    p = np.asarray(p, float)
    k = int(np.argmin(np.abs(YS - p[1])))
    if abs(ZS[k] - p[2]) <= 0.5:
        return k, abs(p[0] - 0.5)
    k = int(np.argmin((YS - p[1]) ** 2 + (4.0 * (ZS - p[2])) ** 2))
    return k, math.hypot(p[0] - 0.5, YS[k] - p[1])


def stair_geodesic(a, b) -> float:
    (ka, oa), (kb, ob) = _snap(a), _snap(b)
    return float(abs(ARC[ka] - ARC[kb]) + oa + ob)


def _ctx(y, offsets, goal_y, reference=None):
    pose = Pose(position_m=(0.5, y, float(surface_z(y))), heading_rad=math.pi / 2)
    cands = [Candidate(index=i, dx_m=0.0, dy_m=dy, angle_rad=0.0, distance_m=abs(dy)) for i, dy in enumerate(offsets)]
    cands = with_stop_and_backtrack(cands, pose, None)
    goal = np.array([0.5, goal_y, float(surface_z(goal_y))])
    return StepContext(instruction="go up the stairs", step=0, pose=pose,
                       candidates=build_candidate_views(cands, None, None),
                       trajectory_m=np.asarray([pose.position_m]), max_steps=30,
                       oracle=OracleInfo(goal_m=goal, reference_path_m=reference, geodesic=stair_geodesic))


def test_end_heights_follow_the_flight():
    here = np.array([0.5, 2.4, float(surface_z(2.4))])
    targets = np.array([[0.5, 4.4], [0.5, 2.0], [0.5, 0.4], [0.5, -1.5]])
    z = end_heights(here, targets, stair_geodesic, OracleConfig())
    # Each estimate is on the floor under the target (the snap keeps it within the nav grid's tolerance).
    assert np.all(np.abs(z - surface_z(targets[:, 1])) <= 0.5), z
    # A short move keeps the agent's height when that is on the floor already.
    assert z[1] == pytest.approx(here[2])
    # At the agent's height the move up is off the floor: the geodesic snaps it to a lower tread, far in plan.
    at_agent_height = np.array([0.5, 4.4, here[2]])
    assert stair_geodesic(at_agent_height, at_agent_height) > 1.0


def test_end_heights_leave_flat_floors_alone():
    def euclid(a, b):
        return float(np.linalg.norm(np.asarray(a) - np.asarray(b)))

    here = np.array([1.0, 2.0, 0.3])
    z = end_heights(here, np.array([[4.0, 2.0], [1.0, -1.0]]), euclid, OracleConfig())
    assert np.all(z == 0.3)


@pytest.mark.parametrize("reference", [False, True])
def test_oracle_climbs_the_stairs_towards_an_upstairs_goal(reference):
    # Up the flight (+2 m) or a short step down (-0.4 m): scored at the agent's height the way up snapped
    # to a lower tread and looked worse, so the oracle walked down and up the flight until its budget ended.
    ref = np.array([[0.5, y, float(surface_z(y))] for y in np.linspace(2.4, 7.0, 8)]) if reference else None
    ctx = _ctx(2.4, [2.0, -0.4], goal_y=7.0, reference=ref)
    with POLICIES.create("oracle") as policy:
        d = policy.decide(ctx)
    chosen = ctx.candidate(d.candidate_index)
    assert chosen.kind == CandidateKind.WAYPOINT and chosen.candidate.dy_m == pytest.approx(2.0), d.reasoning
    # And down the flight towards a downstairs goal.
    ctx = _ctx(2.4, [-2.0, 0.4], goal_y=-2.5)
    with POLICIES.create("oracle") as policy:
        d = policy.decide(ctx)
    assert ctx.candidate(d.candidate_index).candidate.dy_m == pytest.approx(-2.0), d.reasoning
