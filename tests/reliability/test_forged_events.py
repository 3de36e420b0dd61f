"""Forged and replayed events of every kind on mission and exploration keys (issue 15, item 3), over
real zenoh into a real gateway (SQLite file, HTTP through TestClient): ids come from the key, terminal
states are final, events never create unknown jobs, seq must increase. None is accepted; the records
stay exactly as they were.

(A well-formed *next* event of a running job is indistinguishable from its worker's own at this layer:
keeping strangers off the event keys is the bus's access control, item 4.)"""

from __future__ import annotations

import itertools

from services.gateway.records import KIND_STATES, JobKind
from shared import keys
from shared.schemas import JobEvent, JobEventKind, JobState
from tests.reliability.live import LIVE_MAP, ROBOT
from tests.waiting import wait_until

KINDS = list(JobEventKind)
STATES = list(JobState)


def publish(live, kind: str, key_id: str, event: JobEvent) -> None:
    key = (keys.MISSION_EVENTS.format(robot=ROBOT, mission=key_id) if kind == "mission"
           else keys.EXPLORATION_EVENTS.format(robot=ROBOT, exploration=key_id))
    live.typed.publish(key, event)


def settle(ingest, before: int, n: int) -> None:
    """Wait until the ingest has handled ``n`` more events (stored, duplicate or rejected)."""
    def handled():
        return ingest.stored + ingest.duplicates + sum(ingest.rejected.values())
    wait_until(lambda: handled() >= before + n, 20, f"{n} events handled by the gateway")


def handled(ingest) -> int:
    return ingest.stored + ingest.duplicates + sum(ingest.rejected.values())


def record(client, kind: str, job_id: str) -> dict:
    r = client.get(f"/{kind}s/{job_id}").json()
    return {k: r.get(k) for k in ("state", "step", "last_seq", "error", "finished_s")}


def test_forged_and_replayed_events_of_every_kind_are_never_accepted(live, live_gateway, tally):
    with live_gateway() as client:
        ingest = client.app.state.ingest
        store = client.app.state.store
        # A real mission, run to its end by the live planner.
        r = client.post("/missions", json={"instruction": "Walk into the next room and stop.", "map_id": LIVE_MAP,
                                           "options": {"max_steps": 2}})
        assert r.status_code == 202, r.text
        mission = r.json()["id"]
        wait_until(lambda: client.get(f"/missions/{mission}").json()["state"] in ("succeeded", "failed", "cancelled"),
                   120, "the mission ended")
        ended = record(client, "mission", mission)
        history = client.get(f"/missions/{mission}/history").json()
        # An exploration the gateway knows, still running (its row as the gateway creates it).
        store.create_job(JobKind.EXPLORATION, "x-live", {"map_id": LIVE_MAP})
        start = handled(ingest)
        publish(live, "exploration", "x-live", JobEvent(job_id="x-live", seq=0, kind=JobEventKind.STARTED,
                                                            state=JobState.RUNNING))
        settle(ingest, start, 1)
        running = record(client, "exploration", "x-live")
        assert running["state"] == "running" and ingest.stored >= 1

        forged: list[tuple[str, str, JobEvent]] = []
        for kind, state in itertools.product(KINDS, STATES):
            # On the finished mission: every kind and state, next seq, step 999.
            forged.append(("mission", mission, JobEvent(job_id=mission, seq=ended["last_seq"] + 1, kind=kind,
                                                            state=state, step=999)))
            # An unknown id, and an event on mission A's key naming B: neither may create a job.
            forged.append(("mission", "m-unknown", JobEvent(job_id="m-unknown", seq=0, kind=kind, state=state)))
            forged.append(("mission", mission, JobEvent(job_id="m-other", seq=0, kind=kind, state=state)))
            forged.append(("exploration", "x-unknown", JobEvent(job_id="x-unknown", seq=0, kind=kind,
                                                                    state=state)))
            forged.append(("exploration", "x-live", JobEvent(job_id="x-other", seq=1, kind=kind, state=state)))
            # The mission's id on the exploration key (the wrong kind of job).
            forged.append(("exploration", mission, JobEvent(job_id=mission, seq=99, kind=kind, state=state)))
        # On the running exploration: a kind that contradicts its state.
        for kind, state in itertools.product(KINDS, STATES):
            if state in KIND_STATES[kind]:
                continue
            forged.append(("exploration", "x-live", JobEvent(job_id="x-live", seq=1, kind=kind, state=state)))
        # Replays: every stored event of the mission again, and altered copies of old seqs.
        replayed = [("mission", mission, JobEvent(job_id=mission, seq=e["seq"], kind=e["kind"], state=e["state"],
                                                      step=e["step"], data=e["data"])) for e in history]
        replayed += [("mission", mission, JobEvent(job_id=mission, seq=e["seq"], kind=JobEventKind.STEP,
                                                       state=JobState.RUNNING, step=999)) for e in history]
        replayed.append(("exploration", "x-live", JobEvent(job_id="x-live", seq=0, kind=JobEventKind.PROGRESS,
                                                               state=JobState.RUNNING, step=5)))
        start = handled(ingest)
        stored_before = ingest.stored
        for kind, key_id, ev in forged + replayed:
            publish(live, kind, key_id, ev)
        settle(ingest, start, len(forged) + len(replayed))
        accepted = ingest.stored - stored_before
        tally.add("forged_events_sent", len(forged))
        tally.add("replayed_events_sent", len(replayed))
        tally.add("forged_or_replayed_accepted", accepted)
        assert accepted == 0, dict(ingest.rejected)
        assert record(client, "mission", mission) == ended
        assert record(client, "exploration", "x-live") == running
        for kind, job in (("mission", "m-unknown"), ("mission", "m-other"), ("exploration", "x-unknown"),
                          ("exploration", "x-other")):
            assert client.get(f"/{kind}s/{job}").status_code == 404, job
        assert client.get(f"/explorations/{mission}").status_code == 404
        assert len(client.get(f"/missions/{mission}/history").json()) == len(history)
        assert {"terminal", "unknown_job", "id_mismatch", "kind_state"} <= set(ingest.rejected)
        # The real next events of the running exploration are still taken, and its end is final.
        publish(live, "exploration", "x-live", JobEvent(job_id="x-live", seq=1, kind=JobEventKind.FINISHED,
                                                            state=JobState.SUCCEEDED))
        wait_until(lambda: record(client, "exploration", "x-live")["state"] == "succeeded", 20, "exploration ended")
        start = handled(ingest)
        publish(live, "exploration", "x-live", JobEvent(job_id="x-live", seq=2, kind=JobEventKind.STEP,
                                                            state=JobState.RUNNING, step=3))
        settle(ingest, start, 1)
        assert record(client, "exploration", "x-live")["state"] == "succeeded"
