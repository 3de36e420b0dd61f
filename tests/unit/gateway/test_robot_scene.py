"""GET/POST /robot/scene against a scripted robot-io: switches, bad specs, auth, 409 while jobs run."""

from __future__ import annotations

import threading

import pytest

from tests.doubles.scripted_services import ScriptedRobotIo
from shared.bus import FakeBus
from shared.bus.typed import TypedBus
from tests.unit.gateway.conftest import World, wait_state
from tests.waiting import wait_until


@pytest.fixture
def robot_io(net):
    bus = FakeBus(net)
    io = ScriptedRobotIo(TypedBus(bus, "scripted-io"), scene="generated:3")
    yield io
    io.close()
    bus.close()


def test_get_scene_reports_the_current_scene(robot_io, gateway):
    with gateway() as client:
        r = client.get("/robot/scene")
    assert r.status_code == 200
    body = r.json()
    assert body["scene"] == "generated:3" and body["floors"] == 1 and len(body["rooms"]) == 3


def test_post_scene_switches_and_get_follows(robot_io, gateway):
    with gateway() as client:
        r = client.post("/robot/scene", json={"scene": "generated:7:floors=2"})
        assert r.status_code == 200, r.text
        assert r.json()["scene"] == "generated:7:floors=2" and r.json()["floors"] == 2
        assert client.get("/robot/scene").json()["scene"] == "generated:7:floors=2"
    assert robot_io.loaded == ["generated:7:floors=2"]


@pytest.mark.parametrize("body, status", [
    ({"scene": "mp3d/nowhere.glb"}, 422),   # robot-io refuses it
    ({"scene": "generated:1:floors=9"}, 422),
    ({"scene": ""}, 422),                   # the gateway refuses it
    ({"scene": "generated:1\nx"}, 422),
    ({"scene": "generated:1", "extra": 1}, 422),
    ({}, 422),
])
def test_bad_specs_are_4xx_and_change_nothing(robot_io, gateway, body, status):
    with gateway() as client:
        r = client.post("/robot/scene", json=body)
        assert r.status_code == status, r.text
        assert client.get("/robot/scene").json()["scene"] == "generated:3"
    assert robot_io.loaded == []


def test_switching_needs_the_token_when_one_is_set(robot_io, gateway):
    with gateway(api_token="s3cret") as client:
        assert client.post("/robot/scene", json={"scene": "generated:2"}).status_code == 401
        assert client.post("/robot/scene", json={"scene": "generated:2"},
                           headers={"Authorization": "Bearer nope"}).status_code == 401
        assert client.get("/robot/scene").status_code == 200  # reading is open
        r = client.post("/robot/scene", json={"scene": "generated:2"}, headers={"Authorization": "Bearer s3cret"})
        assert r.status_code == 200
    assert robot_io.loaded == ["generated:2"]


def test_no_robot_io_is_503(gateway):
    with gateway() as client:
        assert client.get("/robot/scene").status_code == 503
        assert client.post("/robot/scene", json={"scene": "generated:2"}).status_code == 503


def test_409_while_a_mission_runs_then_allowed_once_it_ended(net, robot_io, gateway):
    w = World(net, steps=40, step_interval_s=0.05)
    try:
        with gateway() as client:
            mid = client.post("/missions", json={"instruction": "go to the kitchen", "map_id": "house"}).json()["id"]
            r = client.post("/robot/scene", json={"scene": "generated:5"})
            assert r.status_code == 409 and mid in r.json()["detail"]
            client.post(f"/missions/{mid}/cancel")
            wait_state(client, mid)
            assert client.post("/robot/scene", json={"scene": "generated:5"}).status_code == 200
    finally:
        w.close()
    assert robot_io.loaded == ["generated:5"]


def test_409_while_an_exploration_runs(net, robot_io, gateway):
    from tests.doubles.scripted_services import ScriptedMapper

    bus = FakeBus(net)
    mapper = ScriptedMapper(TypedBus(bus, "slow-mapper"), stages=3, stage_interval_s=0.5)
    try:
        with gateway() as client:
            xid = client.post("/explorations", json={"map_id": "new"}).json()["id"]
            r = client.post("/robot/scene", json={"scene": "generated:5"})
            assert r.status_code == 409 and xid in r.json()["detail"]
    finally:
        mapper.close()
        bus.close()
    assert robot_io.loaded == []


def test_jobs_and_a_second_switch_are_refused_while_a_scene_loads(net, gateway):
    bus = FakeBus(net)
    loaded = threading.Event()  # the switch lasts until the refusals below are seen
    io = ScriptedRobotIo(TypedBus(bus, "slow-io"), load_gate=loaded)
    w = World(net)
    try:
        with gateway() as client:
            result = {}
            t = threading.Thread(target=lambda: result.update(
                r=client.post("/robot/scene", json={"scene": "generated:9"})))
            t.start()
            try:
                wait_until(lambda: client.app.state.scene_lock.locked(), 5.0, "the switch to start")
                assert client.post("/robot/scene", json={"scene": "generated:8"}).status_code == 409
                m = client.post("/missions", json={"instruction": "go to the kitchen", "map_id": "house"})
                assert m.status_code == 409 and "switching scenes" in m.json()["detail"]
                assert client.post("/explorations", json={"map_id": "other"}).status_code == 409
            finally:
                loaded.set()  # also when an assertion failed: the gateway waits for the switch's request on exit
                t.join(10)
            assert result["r"].status_code == 200
            # Refused submissions leave nothing behind, and jobs start again once the switch is done.
            assert client.get("/missions").json()["total"] == 0
            assert client.post("/missions", json={"instruction": "go to the kitchen", "map_id": "house"}
                               ).status_code == 202
    finally:
        w.close()
        io.close()
        bus.close()
    assert io.loaded == ["generated:9"]
