"""Outcomes that do not lie and messages that are right (issue 15, items 6 and 7), on a real SQLite
store and real zenoh peers: how a mission ended is kept apart from success (which exists only with a
goal); final events keep the step count; a query that ended early does not claim a full timeout."""

from __future__ import annotations

import time

import pytest

from services.gateway.records import JobKind, MissionOutcome
from services.gateway.routes.missions import mission_record
from services.gateway.store import GatewayStore
from shared.bus.typed import NoReplyError, TypedBus
from shared.events import EventStream
from shared.schemas import (
    Candidate, CandidateKind, Decision, EpisodeMetricsData, JobCancelled, JobFailed, JobEvent, JobEventKind,
    MissionFinished, MissionStarted, JobState, MissionStep, MissionOptions, Pose, Ping,
)

POSE = Pose(position_m=(1.0, 1.0, 0.0))
K, S = JobEventKind, JobState


def step(seq: int, kinds: list[CandidateKind]) -> JobEvent:
    cands = [Candidate(index=i, kind=k, dx_m=0.5 if k == CandidateKind.WAYPOINT else 0.0) for i, k in enumerate(kinds)]
    stop = next(i for i, k in enumerate(kinds) if k == CandidateKind.STOP)
    return JobEvent(job_id="m1", seq=seq, kind=K.STEP, state=S.RUNNING, step=seq, data=MissionStep(
        pose=POSE, candidates=cands, decision=Decision(candidate_index=stop, kind=CandidateKind.STOP)))


def metrics(success: bool) -> EpisodeMetricsData:
    return EpisodeMetricsData(ne_m=1.0 if success else 9.0, success=success, oracle_success=success, oracle_ne_m=1.0,
                              tl_m=2.0, spl=0.5 if success else 0.0, ndtw=0.5, sdtw=0.2, shortest_m=2.0,
                              stop_called=True, steps=1, goal_reachable=True)


CASES = [
    # (events after started, state, outcome, success)
    ([step(1, [CandidateKind.WAYPOINT, CandidateKind.STOP]),
      (K.FINISHED, S.SUCCEEDED, MissionFinished(stop_called=True, steps=1))], "succeeded", "policy_stopped", None),
    ([step(1, [CandidateKind.STOP]),
      (K.FINISHED, S.SUCCEEDED, MissionFinished(stop_called=True, steps=1, outcome="no_way_to_move", reason="boxed in"))],
     "succeeded", "no_way_to_move", None),
    # The planner's word, not a guess from the last step's candidates: it knows when it was boxed in.
    ([step(1, [CandidateKind.STOP]),
      (K.FINISHED, S.SUCCEEDED, MissionFinished(stop_called=True, steps=1, outcome="policy_stopped"))],
     "succeeded", "policy_stopped", None),
    ([step(1, [CandidateKind.WAYPOINT, CandidateKind.STOP]),
      (K.FINISHED, S.SUCCEEDED, MissionFinished(stop_called=True, steps=1, outcome="no_way_to_move"))],
     "succeeded", "no_way_to_move", None),
    ([step(1, [CandidateKind.WAYPOINT, CandidateKind.STOP]),
      (K.FINISHED, S.SUCCEEDED, MissionFinished(stop_called=True, steps=1, metrics=metrics(True)))],
     "succeeded", "policy_stopped", True),
    ([step(1, [CandidateKind.WAYPOINT, CandidateKind.STOP]),
      (K.FINISHED, S.SUCCEEDED, MissionFinished(stop_called=True, steps=1, metrics=metrics(False)))],
     "succeeded", "policy_stopped", False),
    ([(K.FINISHED, S.FAILED, MissionFinished(stop_called=False, steps=40, error="step budget of 40 exhausted"))],
     "failed", "max_steps", None),
    ([(K.FINISHED, S.CANCELLED, JobCancelled())], "cancelled", "cancelled", None),
    ([(K.ERROR, S.FAILED, JobFailed(error="boom"))], "failed", "failed", None),
]


@pytest.mark.parametrize("events,state,outcome,success", CASES)
def test_how_a_mission_ended_is_apart_from_success(tmp_path, events, state, outcome, success):
    with GatewayStore(tmp_path / "gw.sqlite3") as store:
        store.create_job(JobKind.MISSION, "m1", {"instruction": "go", "map_id": "h"})
        store.append_event(JobKind.MISSION, JobEvent(job_id="m1", seq=0, kind=K.STARTED, state=S.RUNNING,
                                                         data=MissionStarted(pose=POSE, instruction="go", map_id="h",
                                                                             options=MissionOptions())))
        seq = 1
        for ev in events:
            if isinstance(ev, tuple):
                kind, st, data = ev
                ev = JobEvent(job_id="m1", seq=seq, kind=kind, state=st, step=seq, data=data)
            store.append_event(JobKind.MISSION, ev)
            seq += 1
        rec = mission_record(store.get_job("m1"))
    assert (rec.state.value, rec.outcome, rec.success) == (state, MissionOutcome(outcome), success)


def test_a_job_ended_by_the_gateway_gets_the_outcome_its_state_implies(tmp_path):
    with GatewayStore(tmp_path / "gw.sqlite3") as store:
        store.create_job(JobKind.MISSION, "m1", {})
        store.mark("m1", JobState.CANCELLED)
        assert mission_record(store.get_job("m1")).outcome == MissionOutcome.CANCELLED
        assert mission_record(store.get_job("m1")).success is None


def test_final_events_carry_the_steps_walked(peers):
    a, _ = peers
    stream = EventStream(TypedBus(a), "ant/robot0/missions/m1/events", "m1")
    stream.emit(K.STEP, S.RUNNING, step=7, data=step(7, [CandidateKind.STOP]).data)
    cancelled = stream.emit(K.FINISHED, S.CANCELLED, data=JobCancelled())
    failed = EventStream(TypedBus(a), "ant/robot0/missions/m2/events", "m2")
    failed.emit(K.STEP, S.RUNNING, step=3, data=step(3, [CandidateKind.STOP]).data)
    assert cancelled.step == 7 and failed.emit(K.ERROR, S.FAILED, data=JobFailed(error="x")).step == 3


def test_a_query_nobody_answers_does_not_claim_it_waited_its_timeout(peers):
    a, _ = peers
    t0 = time.monotonic()
    with pytest.raises(NoReplyError) as err:
        TypedBus(a).request("ant/robot0/io/nobody-serves-this", Ping(), Ping, timeout_s=30.0)
    elapsed = time.monotonic() - t0
    if elapsed < 27:  # zenoh ended the query early (no queryable): the message must say so
        assert "within 30.0 s" not in err.value.message and "nobody serves it" in err.value.message
    else:
        assert "within 30.0 s" in err.value.message


@pytest.mark.parametrize("fields,why", [
    ({"stop_called": False, "outcome": "policy_stopped"}, "disagrees with stop_called"),
    ({"stop_called": True, "outcome": "max_steps"}, "disagrees with stop_called"),
    ({"stop_called": True, "outcome": "cancelled"}, "its own event"),
    ({"stop_called": True, "success": True}, "only when a goal is known"),
    ({"stop_called": True, "success": True, "metrics": metrics(False)}, "disagrees with the metrics"),
])
def test_a_finished_event_that_contradicts_itself_is_refused(fields, why):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=why):
        MissionFinished(steps=1, **fields)


def test_a_finished_event_carries_outcome_and_success_on_the_wire():
    from shared.codec import decode, encode

    ev = JobEvent(job_id="m1", seq=1, kind=K.FINISHED, state=S.SUCCEEDED, step=3,
                  data=MissionFinished(stop_called=True, steps=3, metrics=metrics(True)))
    got = decode(encode(ev), JobEvent).data
    assert (got.outcome, got.success) == (MissionOutcome.POLICY_STOPPED, True)
