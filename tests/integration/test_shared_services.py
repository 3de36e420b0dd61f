"""One planner and one mapper serving two robots at once (the fleet design of issue 17).

Real robot-io, mapper and planner services on the in-memory bus, two robots (robot0, robot1) on two
different generated houses; the map store is the scripted one (the planner only asks it for the map's
labels). Requests are routed by the robot id of the key they come on, never by their payload.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from services.mapper.service import MapperService, MapperSettings
from services.planner.service import PlannerService, PlannerSettings
from services.robot_io.service import RobotIoService, RobotIoSettings
from shared import keys
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import RemoteError, TypedBus
from shared.clients import MapperClient, PlannerClient, RobotClient
from shared.runner import RunningService
from shared.schemas import (
    CancelRequest, ErrorCode, JobAccepted, JobEvent, JobState, MissionOptions, MissionRequest, Pose,
)
from tests.doubles.scripted_services import ScriptedReconstructor

CAM = {"width_px": 64, "height_px": 64, "hfov_deg": 90.0}
ROBOTS = {"robot0": "generated:0", "robot1": "generated:1"}
TERMINAL = {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED}


@pytest.fixture(scope="module")
def fleet():
    net = FakeNetwork()
    store = ScriptedReconstructor(TypedBus(FakeBus(net)))
    store.add("m", np.zeros((10, 3), np.float32), np.zeros((10, 3), np.uint8))
    ios = {r: RobotIoService(RobotIoSettings(instance=f"io-{r}", robot=r, robot_config={"scene": scene, "camera": CAM}))
           for r, scene in ROBOTS.items()}
    services = [RunningService(io, FakeBus(net)) for io in ios.values()]
    mapper = MapperService(MapperSettings(instance="map-1"))
    planner = PlannerService(PlannerSettings(instance="plan-1", call_timeout_s=30.0))
    services += [RunningService(mapper, FakeBus(net)), RunningService(planner, FakeBus(net))]
    yield net, planner, ios
    for s in reversed(services):
        s.close()


class Events:
    """Every mission event of one robot, as the gateway would see them."""

    def __init__(self, bus: TypedBus, robot: str):
        self.by_mission: dict[str, list[JobEvent]] = {}
        self._cv = threading.Condition()
        self._sub = bus.subscribe(keys.MISSION_EVENTS.pattern(robot=robot), JobEvent, self._on)

    def _on(self, _key: str, ev: JobEvent) -> None:
        with self._cv:
            self.by_mission.setdefault(ev.job_id, []).append(ev)
            self._cv.notify_all()

    def end(self, mission: str, timeout_s: float = 60.0) -> JobEvent:
        with self._cv:
            ok = self._cv.wait_for(lambda: any(e.state in TERMINAL for e in self.by_mission.get(mission, [])),
                                   timeout_s)
            assert ok, f"mission {mission} did not end within {timeout_s} s"
            return next(e for e in self.by_mission[mission] if e.state in TERMINAL)

    def close(self) -> None:
        self._sub.close()


def _mission(mid: str, start: Pose, steps: int = 3) -> MissionRequest:
    return MissionRequest(mission_id=mid, instruction="walk ahead and stop", map_id="m", options=MissionOptions(
        policy="heuristic", max_steps=steps, anticipation=False, spatial_map=False, start_pose=start))


def test_one_mapper_predicts_for_each_robot_on_its_own_key(fleet):
    net, *_ = fleet
    bus = TypedBus(FakeBus(net))
    for robot in ROBOTS:
        pano = RobotClient(bus, robot).observe()
        cands = MapperClient(bus, robot).predict(pano)
        assert 1 <= len(cands) <= 5


def test_one_planner_runs_two_robots_missions_at_once(fleet, monkeypatch):
    net, planner, ios = fleet
    bus = TypedBus(FakeBus(net))
    clients = {r: RobotClient(bus, r) for r in ROBOTS}
    starts = {r: c.reset() for r, c in clients.items()}
    events = {r: Events(bus, r) for r in ROBOTS}
    # Each mission waits in its first observation until the other's is there too: a planner that ran one
    # robot's mission after the other's could never have both in a step at once. (Comparing the missions'
    # start and end times instead failed on a loaded machine, where a 0.2 s mission can run whole while
    # the other robot's thread waits for a core.)
    both, met = threading.Barrier(2), {}

    def first_waits(robot, observe):
        def observe_(*args, **kwargs):
            if robot not in met:
                try:
                    both.wait(60)  # a bound only: the other mission's first observation ends it
                    met[robot] = True
                except threading.BrokenBarrierError:
                    met[robot] = False
            return observe(*args, **kwargs)
        return observe_

    for r in ROBOTS:
        monkeypatch.setattr(ios[r].robot, "observe", first_waits(r, ios[r].robot.observe))
    try:
        # The same mission id on both robots: each robot has its own queue, so neither is refused.
        for r in ROBOTS:
            assert PlannerClient(bus, r).submit(_mission("same-id", starts[r])).accepted
        assert set(planner.active()) == set(ROBOTS)
        ends = {r: events[r].end("same-id", timeout_s=120) for r in ROBOTS}
        monkeypatch.undo()
        # Concurrent, not one after the other: both missions were inside a step at the same time.
        assert met == {"robot0": True, "robot1": True}
        for r in ROBOTS:
            assert ends[r].state in (JobState.SUCCEEDED, JobState.FAILED)
            traj = np.asarray(ends[r].data.trajectory_m)
            # Each mission drove its own robot: its trajectory ends where that robot now stands.
            assert np.allclose(traj[-1][:2], clients[r].observe().pose.xyz[:2], atol=1e-3)
        assert not np.allclose(starts["robot0"].xyz, starts["robot1"].xyz)  # two houses, two bodies
    finally:
        for e in events.values():
            e.close()


def test_a_request_on_one_robots_key_cannot_touch_another_robot(fleet):
    net, *_ = fleet
    bus = TypedBus(FakeBus(net))
    r0, r1 = RobotClient(bus, "robot0"), RobotClient(bus, "robot1")
    start0, start1 = r0.reset(), r1.reset()
    ev0 = Events(bus, "robot0")
    try:
        assert PlannerClient(bus, "robot0").submit(_mission("iso", start0, steps=4)).accepted
        # robot1's cancel key does not reach robot0's mission, even with its id.
        answers = PlannerClient(bus, "robot1").cancel_everywhere("iso")
        assert answers and all(isinstance(a, JobAccepted) and not a.accepted for a in answers)
        end = ev0.end("iso")
        assert end.state != JobState.CANCELLED
        assert np.allclose(r1.observe().pose.xyz, start1.xyz)  # robot1 never moved
    finally:
        ev0.close()
    # A wildcard asked in the robot segment names no robot: refused, nothing started.
    for key in (keys.MISSION_SUBMIT.pattern(), "ant/*/planner/missions/submit"):
        with pytest.raises(RemoteError) as exc:
            bus.request(key, _mission("wild", start0), JobAccepted, timeout_s=10)
        assert exc.value.code == ErrorCode.BAD_REQUEST
    with pytest.raises(RemoteError) as exc:
        bus.request(keys.MISSION_CANCEL.pattern(), CancelRequest(mission_id="iso"), JobAccepted, timeout_s=10)
    assert exc.value.code == ErrorCode.BAD_REQUEST


def test_planner_replicas_split_robots_by_serve_robots():
    """Two planners given disjoint robots: each robot's missions reach its own planner only."""
    net = FakeNetwork()
    a = PlannerService(PlannerSettings(instance="plan-a", serve_robots=["robot0"]))
    b = PlannerService(PlannerSettings(instance="plan-b", serve_robots=["robot1"]))
    with RunningService(a, FakeBus(net)), RunningService(b, FakeBus(net)):
        bus = TypedBus(FakeBus(net))
        # No robot-io runs: the missions fail at once, but each lands on the planner that serves its robot.
        for r in ("robot0", "robot1"):
            assert PlannerClient(bus, r, timeout_s=5).submit(_mission("m1", Pose(position_m=(0.0, 0.0, 0.0)))).accepted
        time.sleep(0.05)
        with pytest.raises(RemoteError) as exc:
            PlannerClient(bus, "robot2", timeout_s=0.5).submit(_mission("m2", Pose(position_m=(0.0, 0.0, 0.0))))
        assert exc.value.code == ErrorCode.UNAVAILABLE  # nobody serves robot2
    assert set(a._jobs) == {"robot0"} and set(b._jobs) == {"robot1"}
