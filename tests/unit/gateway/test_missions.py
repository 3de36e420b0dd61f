"""Missions over the HTTP API against a scripted planner on a FakeBus."""

from __future__ import annotations

import json
import threading

import pytest

from tests.unit.gateway.conftest import wait_state
from tests.waiting import wait_until


def submit(client, **over):
    body = {"instruction": "Go to the kitchen and stop by the fridge.", "map_id": "house"} | over
    return client.post("/missions", json=body)


def sse_events(text: str) -> list[dict]:
    out = []
    for block in text.split("\n\n"):
        fields = dict(line.split(": ", 1) for line in block.splitlines() if ": " in line and not line.startswith(":"))
        if "data" in fields:
            out.append({"id": fields.get("id"), "event": fields.get("event"), "data": json.loads(fields["data"])})
    return out


def test_mission_runs_to_the_end_and_its_record_is_derived_from_events(world, gateway):
    with gateway() as client:
        r = submit(client, options={"goal_m": [1.0, 1.0, 0.0]})
        assert r.status_code == 202
        created = r.json()
        assert r.headers["location"] == created["url"] == f"/missions/{created['id']}"
        rec = wait_state(client, created["id"])
    assert rec["state"] == "succeeded" and rec["step"] == 3 and rec["last_seq"] == 4
    assert [d["step"] for d in rec["decisions"]] == [1, 2, 3]
    assert rec["decisions"][-1]["kind"] == "stop" and "stop" in rec["decisions"][-1]["reasoning"].lower()
    assert rec["trajectory"][0] == [0.0, 0.0, 0.0] and len(rec["trajectory"]) == 3
    assert rec["prompt_tokens"] == 810 + 820 + 830 and rec["completion_tokens"] == 180
    assert rec["cost_usd"] == pytest.approx(0.003)
    assert set(rec["metrics"]) >= {"ne_m", "success", "spl"}
    assert rec["images"]["panorama"].endswith("/events/3/images/panorama.jpg")


def test_no_metrics_without_a_goal(world, gateway):
    with gateway() as client:
        rec = wait_state(client, submit(client).json()["id"])
    assert rec["state"] == "succeeded" and rec["metrics"] is None


def test_images_are_served_as_jpeg_and_missing_ones_404(world, gateway):
    with gateway() as client:
        rec = wait_state(client, submit(client).json()["id"])
        img = client.get(rec["images"]["cand_1_anticipated"])
        assert img.status_code == 200 and img.headers["content-type"] == "image/jpeg"
        assert img.content[:2] == b"\xff\xd8" and "immutable" in img.headers["cache-control"]
        assert client.get(f"/missions/{rec['id']}/events/0/images/panorama.jpg").status_code == 404
        assert client.get(f"/missions/{rec['id']}/events/1/images/bad$name.jpg").status_code == 422


def test_sse_replays_from_the_db_and_resumes_after_last_event_id(world, gateway):
    with gateway() as client:
        mid = submit(client).json()["id"]
        wait_state(client, mid)
        with client.stream("GET", f"/missions/{mid}/events") as s:
            assert s.headers["content-type"].startswith("text/event-stream")
            events = sse_events(s.read().decode())
        assert [e["id"] for e in events[:-1]] == ["0", "1", "2", "3", "4"]
        assert events[-1]["event"] == "end" and events[-1]["data"]["state"] == "succeeded"
        step = events[1]["data"]
        assert step["kind"] == "step" and step["images"]["map"] == f"/missions/{mid}/events/1/images/map.jpg"
        with client.stream("GET", f"/missions/{mid}/events", headers={"Last-Event-ID": "2"}) as s:
            resumed = sse_events(s.read().decode())
        assert [e["id"] for e in resumed[:-1]] == ["3", "4"]
        with client.stream("GET", f"/missions/{mid}/events?after=3") as s:
            assert [e["id"] for e in sse_events(s.read().decode())[:-1]] == ["4"]
        assert client.get(f"/missions/{mid}/events", headers={"Last-Event-ID": "x"}).status_code == 400
        assert client.get("/missions/m-nope/events").status_code == 404


def test_sse_streams_live_events_as_they_happen(net, gateway):
    from tests.unit.gateway.conftest import World

    w = World(net, steps=4)
    # The mission holds its finish until step 1 has come through the stream: a stream that held events back
    # until the end would show step 1 only after the gate's 10 s, with the mission ended.
    w.planner.finish_gate = stepped = threading.Event()
    try:
        with gateway() as client:
            mid = submit(client).json()["id"]
            seen = []
            with client.stream("GET", f"/missions/{mid}/events") as s:
                buf = ""
                for chunk in s.iter_text():
                    buf += chunk
                    while "\n\n" in buf:
                        block, buf = buf.split("\n\n", 1)
                        seen += sse_events(block + "\n\n")
                        if seen and seen[-1]["id"] == "1":
                            # The stream delivered step 1 while the mission was still running.
                            assert client.get(f"/missions/{mid}").json()["state"] == "running"
                            stepped.set()
            assert [e["id"] for e in seen[:-1]] == ["0", "1", "2", "3", "4", "5"]
    finally:
        stepped.set()
        w.close()


def test_list_is_paged_and_filtered_by_state(world, gateway):
    with gateway() as client:
        ids = [submit(client).json()["id"] for _ in range(3)]
        for mid in ids:
            wait_state(client, mid)
        page = client.get("/missions?limit=2").json()
        assert page["total"] == 3 and len(page["items"]) == 2
        assert {m["id"] for m in page["items"]} | {client.get("/missions?limit=2&offset=2").json()["items"][0]["id"]} \
            == set(ids)
        assert client.get("/missions?state=succeeded").json()["total"] == 3
        assert client.get("/missions?state=running&state=queued").json()["total"] == 0
        assert client.get("/missions?state=flying").status_code == 422
        assert client.get("/missions?limit=0").status_code == 422


def test_cancel_a_running_mission(net, gateway):
    from tests.unit.gateway.conftest import World

    w = World(net, steps=50, step_interval_s=0.05)
    try:
        with gateway() as client:
            mid = submit(client).json()["id"]
            wait_until(lambda: client.get(f"/missions/{mid}").json()["step"] >= 1, what="first step")
            r = client.post(f"/missions/{mid}/cancel")
            assert r.status_code == 202
            rec = wait_state(client, mid)
            assert rec["state"] == "cancelled" and rec["step"] < 50
            assert client.post(f"/missions/{mid}/cancel").status_code == 409
            assert client.post("/missions/m-unknown/cancel").status_code == 404
    finally:
        w.close()


def test_record_and_events_survive_a_gateway_restart(world, gateway):
    with gateway() as first:
        mid = submit(first).json()["id"]
        before = wait_state(first, mid)
    with gateway() as second:
        after = second.get(f"/missions/{mid}").json()
        assert after == before
        with second.stream("GET", f"/missions/{mid}/events") as s:
            assert [e["id"] for e in sse_events(s.read().decode())[:-1]] == ["0", "1", "2", "3", "4"]
        assert second.get(after["images"]["panorama"]).status_code == 200


def test_events_of_a_mission_the_gateway_did_not_submit_create_nothing(world, gateway):
    # Issue 15: an event for an unknown id used to create a mission. Events never create jobs: the
    # gateway creates a job's row before its service hears of it, so only forgeries lack one.
    from shared import keys
    from shared.schemas import MissionRequest, JobAccepted

    with gateway() as client:
        reply = world.planner.bus.request(keys.MISSION_SUBMIT.format(robot="robot0"),
                                          MissionRequest(mission_id="m-direct", instruction="go", map_id="house"),
                                          JobAccepted)
        assert reply.accepted
        ingest = client.app.state.ingest
        wait_until(lambda: ingest.rejected["unknown_job"] >= 5, 10, "the mission's events refused")
        assert client.get("/missions/m-direct").status_code == 404
        assert client.get("/missions").json()["total"] == 0
