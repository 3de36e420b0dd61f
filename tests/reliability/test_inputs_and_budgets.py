"""Inputs accepted silently and budgets (issue 15, items 7-9), against the live system over real zenoh
and a real gateway app: a start pose or goal off walkable ground is a 422 that gives the distance,
non-finite or huge goals are 422s, an empty or meaningless instruction is a 422, and every request over
a per-request budget (pixels, views, points, frames, bytes) gets the typed ``budget_exceeded`` error
(413 over HTTP) before any work is done."""

from __future__ import annotations

import json

import pytest

from services.gateway.errors import remote_status
from shared import keys
from shared.bus.typed import RemoteError
from shared.schemas import (
    BuildMapRequest, CameraIntrinsics, ErrorCode, JobAccepted, MapChunk, MapChunkRequest, MapInfo, ObserveRequest, Panorama,
    RenderRequest, RenderResult, TourRecording, ViewPose,
)
from tests.reliability.live import LIVE_MAP, ROBOT
from tests.waiting import wait_until


def post_mission(client, options=None, instruction="Walk into the kitchen and stop.", raw: str | None = None):
    if raw is not None:
        return client.post("/missions", content=raw, headers={"Content-Type": "application/json"})
    return client.post("/missions", json={"instruction": instruction, "map_id": LIVE_MAP, "options": options or {}})


def test_start_pose_and_goal_off_walkable_ground_are_422_with_the_distance(live, live_gateway, tally):
    with live_gateway() as client:
        for options, field in (({"start_pose": {"position_m": [1e6, 1e6, 0.0]}}, "start_pose"),
                               ({"goal_m": [3000.0, -40.0, 0.0]}, "goal_m"),
                               ({"start_pose": {"position_m": [2.0, 2.0, 25.0]}}, "start_pose")):
            r = post_mission(client, options)
            tally.add("http_bad_inputs_checked")
            assert r.status_code == 422, r.text
            detail = r.json()["detail"]
            assert field in detail and "m from walkable ground" in detail and "tolerance" in detail, detail
        assert client.get("/missions").json()["total"] == 0  # nothing was created


@pytest.mark.parametrize("raw_goal", ["[NaN, 0, 0]", "[1e400, 0, 0]", "[1e300, 0, 0]", "[-Infinity, 0, 0]"])
def test_non_finite_and_huge_goals_are_422_not_a_traceback(live, live_gateway, raw_goal, tally):
    with live_gateway() as client:
        raw = '{"instruction": "Walk into the kitchen.", "map_id": "%s", "options": {"goal_m": %s}}' % (LIVE_MAP, raw_goal)
        r = post_mission(client, raw=raw)
        tally.add("http_bad_inputs_checked")
        assert r.status_code == 422, r.text
        assert "goal_m" in json.dumps(r.json())
        assert "nan" not in json.dumps(r.json()).lower() or "NaN" in raw_goal


@pytest.mark.parametrize("instruction", ["\u0000", "   ", "?!?", "\u0000\u0000 12"])
def test_an_empty_or_meaningless_instruction_is_422(live, live_gateway, instruction, tally):
    with live_gateway() as client:
        r = post_mission(client, instruction=instruction)
        tally.add("http_bad_inputs_checked")
        assert r.status_code == 422, r.text
        assert client.get("/missions").json()["total"] == 0


def budget_cases(live):
    pano = live.typed.request(keys.IO_OBSERVE.format(robot=ROBOT), ObserveRequest(with_semantic=False), Panorama,
                              timeout_s=20)
    big = CameraIntrinsics(width_px=512, height_px=512)
    tour = TourRecording(exploration_id="x", recording="r", region=0, start_pose=pano.pose, frame_count=400_000)
    return [
        ("render pixels", keys.RENDER_VIEWS.format(),
         RenderRequest(map_id=LIVE_MAP, views=[ViewPose(position_m=pano.pose.position_m)] * 64, camera=big), RenderResult),
        ("render a 4096 px view", keys.RENDER_VIEWS.format(),
         RenderRequest(map_id=LIVE_MAP, views=[ViewPose(position_m=pano.pose.position_m)],
                       camera=CameraIntrinsics(width_px=4096, height_px=4096)), RenderResult),
        ("observe pixels", keys.IO_OBSERVE.format(robot=ROBOT),
         ObserveRequest(camera=CameraIntrinsics(width_px=2048, height_px=2048)), Panorama),
        ("map chunk points", keys.MAP_CHUNK.format(map=LIVE_MAP),
         MapChunkRequest(map_id=LIVE_MAP, max_points=10_000_000), MapChunk),
        ("build frames", keys.MAP_BUILD.format(map="budget-build"),
         BuildMapRequest(build_id="b-budget", exploration_id="x", map_id="budget-build", recordings=[tour, tour]),
         JobAccepted),
    ]


def test_every_budget_is_a_typed_error_before_any_work(live, tally):
    before = live.typed.request(keys.IO_OBSERVE.format(robot=ROBOT), ObserveRequest(with_semantic=False), Panorama,
                                timeout_s=20).pose
    for what, key, req, reply in budget_cases(live):
        tally.add("budget_abuse_attempts")
        with pytest.raises(RemoteError) as err:
            live.typed.request(key, req, reply, timeout_s=20)
        assert err.value.code == ErrorCode.BUDGET_EXCEEDED, (what, err.value)
        assert "per request" in err.value.message, err.value.message
        assert remote_status(err.value) == 413
        tally.add("budget_refused_typed")
    # Nothing moved, the services still serve a normal request.
    after = live.typed.request(keys.IO_OBSERVE.format(robot=ROBOT), ObserveRequest(with_semantic=False), Panorama,
                               timeout_s=20).pose
    assert after == before
    ok = live.typed.request(keys.RENDER_VIEWS.format(), RenderRequest(
        map_id=LIVE_MAP, views=[ViewPose(position_m=before.position_m)] * 4,
        camera=CameraIntrinsics(width_px=64, height_px=64)), RenderResult, timeout_s=20)
    assert ok.rgb.shape == (4, 64, 64, 3)


def test_robot_state_health_shows_in_status(live, live_gateway):
    svc = live.service("robot_io")

    def robot_io(client) -> dict | None:
        body = client.get("/status").json()
        io = [s for s in body["services"] if s["service"] == "robot_io"]
        return io[0]["details"][0] if io and io[0]["details"][0]["healthy"] is not None else None

    with live_gateway() as client:
        assert wait_until(lambda: robot_io(client), 20, "robot-io seen in /status")["healthy"] is True
        saved = svc.robot._pos.copy()
        try:
            svc.robot._pos[:] = float("nan")
            io = wait_until(lambda: robot_io(client), 20, "robot-io seen in /status")
            body = client.get("/status").json()
        finally:
            svc.robot._pos = saved
    assert io["healthy"] is False and "not finite" in io["problem"]
    assert body["all_healthy"] is False


def test_scene_paths_outside_the_configured_directories_reveal_nothing(live, live_gateway, tmp_path):
    existing, missing = "/etc/hostname", "/etc/no-such-file-here.glb"
    with live_gateway() as client:
        answers = [client.post("/robot/scene", json={"scene": p}) for p in (existing, missing, "../../etc/hostname")]
    assert [a.status_code for a in answers] == [422, 422, 422], [a.text for a in answers]
    details = {a.json()["detail"].replace(p, "<path>") for a, p in zip(answers, (existing, missing, "../../etc/hostname"))}
    assert len(details) == 1, details  # the same answer whether the file exists or not
    assert "only generated" in details.pop()  # live robot-io has no scene directory configured
