"""No poisoned state (issue 15, item 1): every number of every request is checked at the schema, so a
non-finite, huge or out-of-range value on *any* queryable is refused with ``bad_request`` - and after
each refusal a probe that does real work (an observe, a render) still works and finds the robot exactly
where it was. A request that fails inside the robot leaves its state as it was; a robot whose state is
broken says so in ``info`` (and ``GET /status``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared import keys
from shared.bus.base import QueryTarget
from shared.bus.typed import RemoteError
from shared.codec import CodecError, decode
from shared.schemas import (
    CameraIntrinsics, ErrorCode, ErrorReply, ObserveRequest, Panorama, Ping, Pose, PoseReply, RenderRequest,
    RenderResult, ResetRequest, ServiceInfo, TurnRequest, ViewPose,
)
from tests.reliability.limits import bad_value_payloads, samples
from tests.reliability.live import LIVE_MAP, ROBOT

PARTS = {"robot": ROBOT, "map": LIVE_MAP}


def ask(live, key: str, payload: bytes) -> ErrorReply | str:
    replies = live.bus.query(key, payload, timeout_s=20.0, target=QueryTarget.BEST)
    if not replies:
        return "no reply"
    if replies[0].ok:
        return "accepted"
    try:
        return decode(replies[0].error, ErrorReply)
    except CodecError:
        return "untyped error"


class Probe:
    """Real work after every fuzzed request: an observe (the pose must not have moved) and a render."""

    def __init__(self, live):
        self.live = live
        self.pose = self.observe().pose

    def observe(self) -> Panorama:
        return self.live.typed.request(keys.IO_OBSERVE.format(robot=ROBOT), ObserveRequest(with_semantic=False),
                                       Panorama, timeout_s=20)

    def check(self, render: bool) -> str | None:
        try:
            pano = self.observe()
            if pano.pose != self.pose:
                return f"the pose moved: {self.pose} -> {pano.pose}"
            if not np.isfinite(pano.depth_m).all() or not pano.depth_m.any():
                return "observe returned no depth"
            if render:
                out = self.live.typed.request(
                    keys.RENDER_VIEWS.format(), RenderRequest(
                        map_id=LIVE_MAP, views=[ViewPose(position_m=pano.pose.position_m,
                                                          heading_rad=pano.pose.heading_rad)],
                        camera=CameraIntrinsics(width_px=32, height_px=32)), RenderResult, timeout_s=20)
                if not out.rgb.any():
                    return "the render is empty"
        except RemoteError as exc:
            return f"probe failed: {exc}"
        return None


def catalogue_targets(live) -> list[tuple[str, str]]:
    out = []
    for k in keys.CATALOGUE:
        if k.usage == keys.Usage.QUERYABLE and "service" not in k.parts:
            out.append((k.format(**{p: PARTS[p] for p in k.parts}), k.request))
    return out


def test_bad_numbers_on_every_queryable_are_refused_and_poison_nothing(live, tally):
    pano = Probe(live).observe()
    by_schema = samples(LIVE_MAP, panorama=pano)
    targets = catalogue_targets(live)
    assert len(targets) >= 18
    probe = Probe(live)
    wrong, poisoned, sent, covered = [], [], 0, set()
    for key, schema in targets:
        sample = by_schema.get(schema)
        if sample is None:
            continue  # a schema without numbers (Ping, LoadSceneRequest, ...)
        covered.add(schema)
        for path, value, payload in bad_value_payloads(sample):
            answer = ask(live, key, payload)
            sent += 1
            if not (isinstance(answer, ErrorReply) and answer.code == ErrorCode.BAD_REQUEST):
                wrong.append((key, path, value, answer))
            problem = probe.check(render=sent % 10 == 0)
            if problem:
                poisoned.append((key, path, value, problem))
    tally.add("bus_numbers_fuzzed", sent)
    tally.add("bus_numbers_refused", sent - len(wrong))
    tally.add("poisoned_states", len(poisoned))
    tally.add("probes_after_fuzz", sent)
    assert not wrong, wrong[:10]
    assert not poisoned, poisoned[:10]
    assert sent >= 200 and {"TurnRequest", "MoveRequest", "ResetRequest", "RenderRequest"} <= covered


def test_turn_by_infinity_is_refused_and_observe_still_works(live):
    """The reported defect itself: turn(inf) used to be accepted, every later observe then failed."""
    probe = Probe(live)
    for angle in (math.inf, -math.inf, math.nan, 1e300):
        with pytest.raises(RemoteError) as err:
            live.typed.request(keys.IO_TURN.format(robot=ROBOT), TurnRequest.model_construct(angle_rad=angle),
                               PoseReply, timeout_s=10)
        assert err.value.code == ErrorCode.BAD_REQUEST
        assert "nan" not in err.value.message.lower() or math.isnan(angle), err.value.message
        assert probe.check(render=True) is None


def test_a_reset_far_from_walkable_ground_is_refused_with_the_distance_and_moves_nothing(live):
    probe = Probe(live)
    with pytest.raises(RemoteError) as err:
        live.typed.request(keys.IO_RESET.format(robot=ROBOT), ResetRequest(pose=Pose(position_m=(5000.0, 5000.0, 0.0))),
                           PoseReply, timeout_s=10)
    assert err.value.code == ErrorCode.BAD_REQUEST and "from walkable ground" in err.value.message
    assert probe.check(render=False) is None


def test_a_request_that_fails_inside_the_robot_leaves_its_state_exactly_as_it_was(live):
    """A motion that fails half-way (here: a recording sink that breaks mid-move) is undone."""
    svc = live.service("robot_io")
    robot = svc.robot
    before = (robot.true_pose, robot.pose, robot.clock_s, robot._frame_index)
    calls = []

    def broken_sink(frame):
        calls.append(frame.index)
        if len(calls) > 2:
            raise OSError("disk full")

    with svc._lock, robot.recording(broken_sink, rate_hz=20.0):
        with pytest.raises(OSError):
            with robot.transaction():
                robot.move_to(1.5, 0.0)
    assert len(calls) > 2  # it really moved part of the way before failing
    assert (robot.true_pose, robot.pose, robot.clock_s, robot._frame_index) == before


def test_a_robot_whose_state_is_broken_does_not_report_itself_healthy(live):
    svc = live.service("robot_io")
    key = keys.INFO.format(service="robot_io", instance="io-live")
    assert live.typed.request(key, Ping(), ServiceInfo, timeout_s=10).healthy is True
    saved = svc.robot._heading
    try:
        svc.robot._heading = float("nan")  # what an accepted turn(inf) used to leave behind
        info = live.typed.request(key, Ping(), ServiceInfo, timeout_s=10)
        assert info.healthy is False and "not finite" in info.problem
    finally:
        svc.robot._heading = saved
    assert live.typed.request(key, Ping(), ServiceInfo, timeout_s=10).healthy is True
