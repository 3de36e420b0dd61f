"""Polling and streaming under load: encoded records per revision with ETag/304, SSE fan-out from the hub."""

from __future__ import annotations

import asyncio
import json
import time

import pytest

from services.gateway.cache import RecordCache, etag_matches
from services.gateway.events import EventHub, event_json, event_json_text, sse_frame, sse_stream
from services.gateway.records import JobKind
from services.gateway.routes.explorations import exploration_record
from services.gateway.routes.missions import mission_record
from services.gateway.store import GatewayStore
from shared.schemas import (
    CandidateKind, Decision, JobEvent, JobEventKind, MissionFinished, JobState, MissionStep, Pose,
)
from tests.unit.gateway.conftest import World, wait_state
from tests.unit.gateway.test_missions import sse_events, submit


def _event(job: str, seq: int, state=JobState.RUNNING) -> JobEvent:
    if state == JobState.SUCCEEDED:
        return JobEvent(job_id=job, seq=seq, kind=JobEventKind.FINISHED, state=state, step=seq,
                            data=MissionFinished(stop_called=True, steps=seq))
    return JobEvent(job_id=job, seq=seq, kind=JobEventKind.STEP, state=state, step=seq,
                        data=MissionStep(pose=Pose(position_m=(float(seq), 0.0, 0.0)), candidates=[],
                                         decision=Decision(candidate_index=0, kind=CandidateKind.WAYPOINT)))


@pytest.fixture
def store(tmp_path):
    with GatewayStore(tmp_path / "gw.sqlite3") as s:
        yield s


def test_polls_get_an_etag_and_304_until_the_record_changes(net, gateway):
    w = World(net, steps=3, step_interval_s=0.01)
    try:
        with gateway() as client:
            mid = submit(client).json()["id"]
            wait_state(client, mid)
            first = client.get(f"/missions/{mid}")
            etag = first.headers["etag"]
            assert first.status_code == 200 and first.headers["cache-control"] == "no-cache"
            again = client.get(f"/missions/{mid}")
            assert again.headers["etag"] == etag and again.content == first.content
            for header in (etag, f"W/{etag}", f'"other", {etag}', "*"):
                r = client.get(f"/missions/{mid}", headers={"If-None-Match": header})
                assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
            assert client.get(f"/missions/{mid}", headers={"If-None-Match": '"stale"'}).status_code == 200
            # The record is the same JSON the response model describes.
            assert first.json()["id"] == mid and first.json()["state"] == "succeeded"
            assert client.get("/missions/m-unknown", headers={"If-None-Match": "*"}).status_code == 404
    finally:
        w.close()


def test_a_new_event_changes_the_record_and_its_etag(net, gateway):
    w = World(net, steps=60, step_interval_s=0.05)
    try:
        with gateway() as client:
            mid = submit(client).json()["id"]
            a = client.get(f"/missions/{mid}")
            b = a
            for _ in range(200):  # until the planner's next event lands
                b = client.get(f"/missions/{mid}", headers={"If-None-Match": a.headers["etag"]})
                if b.status_code == 200:
                    break
                time.sleep(0.02)
            assert b.status_code == 200 and b.headers["etag"] != a.headers["etag"]
            assert b.json()["last_seq"] > a.json()["last_seq"]
            client.post(f"/missions/{mid}/cancel")
            assert wait_state(client, mid)["state"] == "cancelled"
    finally:
        w.close()


def test_cache_follows_every_kind_of_write(store):
    cache = RecordCache(store, max_jobs=2)
    store.create_job(JobKind.MISSION, "m1", {"instruction": "go", "map_id": "house"})
    e0 = cache.get("m1", JobKind.MISSION, mission_record)
    assert cache.get("m1", JobKind.MISSION, mission_record) is e0 and cache.hits == 1
    assert cache.get("m1", JobKind.EXPLORATION, exploration_record) is None  # wrong kind
    store.append_event(JobKind.MISSION, _event("m1", 0))
    e1 = cache.get("m1", JobKind.MISSION, mission_record)
    assert e1.etag != e0.etag and json.loads(e1.body)["last_seq"] == 0
    store.mark("m1", JobState.FAILED, "lost")
    e2 = cache.get("m1", JobKind.MISSION, mission_record)
    assert json.loads(e2.body)["state"] == "failed" and json.loads(e2.body)["error"] == "lost"
    assert store.append_event(JobKind.MISSION, _event("m1", 0)) is None  # a duplicate changes nothing
    assert cache.get("m1", JobKind.MISSION, mission_record) is e2
    store.delete_job("m1")
    assert cache.get("m1", JobKind.MISSION, mission_record) is None
    # Bounded: the least recently used record goes.
    for j in ("a", "b", "c"):
        store.create_job(JobKind.MISSION, j, {})
        cache.get(j, JobKind.MISSION, mission_record)
    assert len(cache._entries) == 2 and "a" not in cache._entries


def test_jobs_written_by_an_earlier_process_are_adopted(tmp_path):
    with GatewayStore(tmp_path / "gw.sqlite3") as old:
        old.create_job(JobKind.MISSION, "m1", {"instruction": "go", "map_id": "house"})
        old.append_event(JobKind.MISSION, _event("m1", 0))
    with GatewayStore(tmp_path / "gw.sqlite3") as store:
        assert store.revision("m1") is None
        assert store.job_progress("m1") == (JobState.RUNNING, 0)
        rev = store.revision("m1")
        row, rev2 = store.get_job_revision("m1")
        assert rev is not None and rev2 == rev and row.last_seq == 0
        store.append_event(JobKind.MISSION, _event("m1", 1, JobState.SUCCEEDED))
        assert store.revision("m1") > rev and store.job_progress("m1") == (JobState.SUCCEEDED, 1)
        assert store.job_progress("nope") is None


def test_etag_matching():
    assert etag_matches('"a"', '"a"') and etag_matches('W/"a"', '"a"') and etag_matches('"x" , "a"', '"a"')
    assert etag_matches("*", '"a"')
    assert not etag_matches(None, '"a"') and not etag_matches('"b"', '"a"') and not etag_matches('a', '"a"')


def test_spliced_event_json_equals_the_plain_encoding(store):
    store.create_job(JobKind.MISSION, "m1", {})
    ev = JobEvent(job_id="m1", seq=0, kind=JobEventKind.STEP, state=JobState.RUNNING, step=1,
                      data=MissionStep(pose=Pose(position_m=(0.0, 0.0, 0.0)), candidates=[], decision=Decision(
                          candidate_index=0, kind=CandidateKind.WAYPOINT, reasoning='say "hi" \u00e9')),
                      images={"panorama": b"\xff\xd8jpeg"})
    stored = store.append_event(JobKind.MISSION, ev)
    (read,) = store.events("m1")
    for e in (stored, read):
        assert json.loads(event_json_text(JobKind.MISSION, e)) == event_json(JobKind.MISSION, e)
    assert sse_frame(JobKind.MISSION, stored) == sse_frame(JobKind.MISSION, read)


def test_hub_keeps_a_bounded_gapless_tail():
    async def run():
        hub = EventHub(asyncio.get_running_loop(), tail_frames=3, tail_jobs=2)
        for seq in (0, 1, 2, 4):
            hub.publish("j", seq, f"f{seq}")
        await asyncio.sleep(0)
        assert [s for s, _ in hub.frames_after("j", -1, 10)] == []  # 0 was evicted (3 kept: 1, 2, 4)
        assert hub.frames_after("j", 0, 10) == [(1, "f1"), (2, "f2")]  # stops at the gap before 4
        assert hub.frames_after("j", 0, 1) == [(1, "f1")]
        assert hub.frames_after("j", 3, 10) == [(4, "f4")]
        hub.publish("k", 0, "k0")
        hub.publish("l", 0, "l0")
        await asyncio.sleep(0)
        assert hub.frames_after("j", 0, 10) == [] and hub.frames_after("l", -1, 10) == [(0, "l0")]
        hub.close()
    asyncio.run(run())


def test_live_streams_share_frames_and_do_not_read_the_db(store, monkeypatch):
    store.create_job(JobKind.MISSION, "m1", {})
    store.append_event(JobKind.MISSION, _event("m1", 0))
    reads = []
    real_events = store.events
    monkeypatch.setattr(store, "events", lambda *a, **k: reads.append(a) or real_events(*a, **k))

    async def run():
        hub = EventHub(asyncio.get_running_loop())

        async def collect():
            out = []
            async for frame in sse_stream(store, hub, JobKind.MISSION, "m1", -1, keepalive_s=5.0, batch=50):
                out.append(frame)
            return out

        streams = [asyncio.create_task(collect()) for _ in range(20)]
        for _ in range(500):  # the replays read in worker threads: up to 5 s on a loaded machine
            if len(reads) >= 20:
                break
            await asyncio.sleep(0.01)
        assert len(reads) == 20  # each replayed event 0 from the database ...
        for seq in range(1, 6):
            stored = store.append_event(JobKind.MISSION, _event("m1", seq, JobState.SUCCEEDED if seq == 5
                                                                 else JobState.RUNNING))
            hub.publish("m1", seq, sse_frame(JobKind.MISSION, stored))
            await asyncio.sleep(0.01)
        results = await asyncio.wait_for(asyncio.gather(*streams), 5.0)
        hub.close()
        return results

    results = asyncio.run(run())
    assert len(reads) == 20  # ... and then got every live event from the hub
    for frames in results:
        events = sse_events("".join(frames))
        assert [e["id"] for e in events[:-1]] == [str(s) for s in range(6)]
        assert events[-1]["event"] == "end" and events[-1]["data"] == {"state": "succeeded", "last_seq": 5}


def test_a_stream_behind_the_hub_reads_the_db_and_misses_nothing(store):
    store.create_job(JobKind.MISSION, "m1", {})

    async def run():
        hub = EventHub(asyncio.get_running_loop(), tail_frames=2)
        for seq in range(6):
            stored = store.append_event(JobKind.MISSION, _event("m1", seq, JobState.SUCCEEDED if seq == 5
                                                                 else JobState.RUNNING))
            hub.publish("m1", seq, sse_frame(JobKind.MISSION, stored))
        await asyncio.sleep(0)
        out = [f async for f in sse_stream(store, hub, JobKind.MISSION, "m1", 0, keepalive_s=1.0, batch=2)]
        hub.close()
        return out

    events = sse_events("".join(asyncio.run(run())))
    assert [e["id"] for e in events[:-1]] == ["1", "2", "3", "4", "5"] and events[-1]["event"] == "end"
