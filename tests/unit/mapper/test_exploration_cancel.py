"""Cancelling an exploration: it stops within one exploration step, between two tour moves, or by
cancelling the map build it waits on; it ends ``cancelled`` with the stage it was in, and leaves no map.

The job runs as the mapper runs it (a :class:`shared.jobs.JobRunner` on the fake bus) in the box-room
world; the robot itself pulls the cancel at a chosen moment (its n-th panorama, its n-th move inside a
recording), so each test knows exactly where the cancel landed, without any timing.
"""

from __future__ import annotations

import contextlib
import threading

import pytest

from services.mapper.core.exploration_job import explore
from services.mapper.service import MapperService, MapperSettings
from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world
from services.reconstructor.service import ReconstructorService, ReconstructorSettings
from services.robot_io.service import RobotIoService, RobotIoSettings
from shared import keys
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import TypedBus
from shared.clients import MapClient, MapperClient, RobotClient
from shared.geometry import PinholeCamera
from shared.jobs import TERMINAL_STATES, JobRunner
from shared.runner import RunningService
from shared.schemas import (
    ExplorationRequest, JobAccepted, JobCancelled, JobEvent, JobState, RecordReply, SceneSummary,
)
from tests.waiting import wait_until

XID = "x-cancel"


class Robot(BoxWorldRobot):
    """The box-world robot as the exploration job sees a robot-io: it records tours (counting their
    frames; nobody receives them) and says what its scene is. ``on_observe(n)`` runs at its n-th
    panorama, ``on_recorded_move(n)`` at its n-th move inside a recording."""

    def __init__(self, on_observe=None, on_recorded_move=None):
        super().__init__(rooms_world(), PinholeCamera(48, 48, 90.0))
        self.on_observe, self.on_recorded_move = on_observe, on_recorded_move
        self.last_recording: RecordReply | None = None
        self.recording_open = False
        self.recorded_moves = 0
        self.recordings = 0

    def observe(self):
        pano = super().observe()
        if self.on_observe is not None:
            self.on_observe(self.observations)
        return pano

    def move_to(self, dx_m: float, dy_m: float):
        res = super().move_to(dx_m, dy_m)
        if self.recording_open:
            self.recorded_moves += 1
            if self.on_recorded_move is not None:
                self.on_recorded_move(self.recorded_moves)
        return res

    @contextlib.contextmanager
    def recording(self, sink=None, rate_hz: float = 5.0):
        frames: list = []
        self.recording_open = True
        try:
            with super().recording(frames.append, rate_hz):
                yield f"{XID}-r{self.recordings}"
        finally:
            self.recording_open = False
            self.last_recording = RecordReply(recording=f"{XID}-r{self.recordings}", recording_on=False,
                                              frame_count=len(frames))
            self.recordings += 1

    def scene(self) -> SceneSummary:
        lo, hi = self.world.bounds()
        return SceneSummary(scene="rooms", bounds_min_m=tuple(map(float, lo)), bounds_max_m=tuple(map(float, hi)),
                            label_names={0: "wall"})


class NoBuilds:
    """A map builder that must never be asked (the exploration was cancelled before its build)."""

    def __init__(self):
        self.asked = 0

    def build(self, req, *, on_event=None, cancel=None):
        self.asked += 1
        raise AssertionError("a cancelled exploration asked for a map build")


@pytest.fixture
def net():
    return FakeNetwork()


class Job:
    """One exploration job on a runner of the fake bus, its events collected on another bus."""

    def __init__(self, net: FakeNetwork, robot: Robot, maps, max_steps: int | None = None):
        self.bus, watcher = TypedBus(FakeBus(net)), TypedBus(FakeBus(net))
        self.events: list[JobEvent] = []
        self.graphs, self.tours = [], []
        watcher.subscribe(keys.EXPLORATION_EVENTS.format(robot="robot0", exploration=XID), JobEvent,
                          lambda _k, ev: self.events.append(ev))
        self._buses = [self.bus, watcher]
        self.runner = JobRunner(self.bus, name="exploration of robot0", workers=1, max_queued=1)
        req = ExplorationRequest(exploration_id=XID, map_id="cancelled-map", max_steps=max_steps)
        self.runner.submit(XID, lambda ctx: explore(ctx, req, robot=robot, maps=maps, tour_rate_hz=4.0,
                                                    publish_graph=self.graphs.append, publish_tour=self.tours.append),
                           keys.EXPLORATION_EVENTS.format(robot="robot0", exploration=XID))

    def cancel(self) -> None:
        assert self.runner.cancel(XID).accepted  # what the mapper's cancel queryable does

    def end(self, timeout_s: float = 120.0) -> JobEvent:
        return wait_until(lambda: next((e for e in self.events if e.state in TERMINAL_STATES), None), timeout_s,
                          "the exploration's end")

    def close(self) -> None:
        self.runner.close()
        for b in self._buses:
            b.close()


def test_a_cancel_mid_discovery_ends_it_within_one_step(net):
    job: Job | None = None
    robot = Robot(on_observe=lambda n: n == 3 and job.cancel())
    maps = NoBuilds()
    job = Job(net, robot, maps)  # no step cap: left alone, it would take ~150 panoramas
    try:
        end = job.end()
    finally:
        job.close()
    # The cancel came during the third panorama; the loop saw it before the next step: no fourth.
    assert robot.observations == 3
    assert end.state == JobState.CANCELLED and isinstance(end.data, JobCancelled)
    assert end.data.stage == "exploring" and "while exploring" in end.data.message
    assert [e.state for e in job.events].count(JobState.CANCELLED) == 1 and end is job.events[-1]
    assert maps.asked == 0 and not job.graphs and not job.tours


def test_a_cancel_during_a_tour_stops_between_two_moves_and_closes_the_recording(net):
    job: Job | None = None
    robot = Robot(on_recorded_move=lambda n: n == 5 and job.cancel())
    maps = NoBuilds()
    job = Job(net, robot, maps, max_steps=8)  # 8 panoramas: two short region tours
    try:
        end = job.end()
    finally:
        job.close()
    assert robot.recorded_moves == 5  # no move after the one the cancel came in
    assert robot.recordings == 1 and not robot.recording_open  # the recording under way was stopped
    assert end.state == JobState.CANCELLED and end.data.stage == "touring"
    assert maps.asked == 0  # no build of a half-toured house


def test_a_cancel_during_the_map_build_cancels_the_build_and_stores_nothing(net, tmp_path):
    # The real reconstructor, whose build waits for frames nobody sends: it sits collecting until cancelled.
    recon = ReconstructorService(ReconstructorSettings(instance="rc-1", store_dir=str(tmp_path / "maps"),
                                                       frames_timeout_s=600.0))
    builds: list[JobEvent] = []
    job: Job | None = None
    with RunningService(recon, FakeBus(net)):
        watcher = TypedBus(FakeBus(net))

        def on_build(_key, ev: JobEvent) -> None:
            builds.append(ev)
            if len(builds) == 1:  # the reconstructor has the build: now cancel the exploration
                job.cancel()

        watcher.subscribe(keys.MAP_BUILD_EVENTS.pattern(), JobEvent, on_build)
        robot = Robot()
        job = Job(net, robot, MapClient(job_bus := TypedBus(FakeBus(net)), build_stall_s=60.0), max_steps=8)
        try:
            end = job.end()
            build_end = wait_until(lambda: next((e for e in builds if e.state in TERMINAL_STATES), None), 30,
                                   "the build's end (cancelled on the reconstructor)")
        finally:
            job.close()
            watcher.close()
            job_bus.close()
        assert recon.store.list() == []  # nothing of the map was stored
    assert robot.recordings >= 1
    assert end.state == JobState.CANCELLED and end.data.stage == "reconstructing"
    # The build was cancelled on the reconstructor (not abandoned), and ended before the exploration did.
    assert build_end.state == JobState.CANCELLED and build_end.data.stage == "collecting"
    assert build_end.timestamp_s <= end.timestamp_s


def test_the_mapper_cancels_only_the_exploration_of_the_robot_whose_key_asks(net):
    """The service end to end on the fake bus: robot-io's simulator in a generated house, the mapper,
    a client in the gateway's place. The robot id comes from the cancel's key."""
    cam = {"width_px": 32, "height_px": 32, "hfov_deg": 90.0}
    io = RobotIoService(RobotIoSettings(instance="io-1", robot_config={"scene": "generated:0", "camera": cam}))
    mapper = MapperService(MapperSettings(instance="map-1", explore_camera_px=32))
    with RunningService(io, FakeBus(net)), RunningService(mapper, FakeBus(net)):
        bus = TypedBus(FakeBus(net))
        # One panorama first, with a generous budget: on a fresh clone robot-io's first observe compiles
        # its render kernels (tens of seconds on a loaded 2-core machine), longer than the mapper's 30 s
        # request budget. What this test checks starts after that.
        RobotClient(bus, "robot0", timeout_s=300.0).observe()
        events: list[JobEvent] = []
        first = threading.Event()

        def on_event(_key, ev: JobEvent) -> None:
            events.append(ev)
            first.set()

        bus.subscribe(keys.EXPLORATION_EVENTS.format(robot="robot0", exploration=XID), JobEvent, on_event)
        client = MapperClient(bus, "robot0")
        assert client.explore(ExplorationRequest(exploration_id=XID, map_id="m")).accepted  # no step cap
        wait_until(first.is_set, 60, "the exploration's first event")
        # robot1's key cannot reach robot0's exploration, even with its id.
        other = MapperClient(bus, "robot1").cancel_everywhere(XID)
        assert other and all(isinstance(a, JobAccepted) and not a.accepted for a in other)
        assert mapper.active() == {"robot0": [XID]}
        answers = client.cancel_everywhere(XID)
        assert [a.accepted for a in answers] == [True]
        end = wait_until(lambda: next((e for e in events if e.state in TERMINAL_STATES), None), 120,
                         "the cancelled event")
        assert end.state == JobState.CANCELLED and end.data.stage == "exploring"
        wait_until(lambda: mapper.active() == {"robot0": []}, 10, "the runner to be free")
        again = client.cancel_everywhere(XID)  # terminal states are final: nothing left to cancel
        assert [a.accepted for a in again] == [False] and "no such" in again[0].reason
        bus.close()
