"""shared.jobs: accept, then typed events, then exactly one terminal state - whatever the body does."""

import threading

import pytest

from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import RemoteError, TypedBus
from shared.jobs import Cancelled, JobEnd, JobFailedError, JobRunner, await_job
from shared.schemas import (
    ExplorationProgress, ExplorationRequest, JobAccepted, JobCancelled, JobEvent, JobEventKind, JobFailed, JobState,
    MapBuildFinished, MapInfo,
)
from tests.waiting import wait_until

KEY = "ant/test/jobs/{}/events"


@pytest.fixture
def buses():
    net = FakeNetwork()
    a, b = TypedBus(FakeBus(net)), TypedBus(FakeBus(net))
    yield a, b
    a.close()
    b.close()


def _collect(bus, job_id):
    got: list[JobEvent] = []
    bus.subscribe(KEY.format(job_id), JobEvent, lambda _k, ev: got.append(ev))
    return got


def _finished(progress=0.5):
    def body(ctx):
        ctx.progress(ExplorationProgress(stage="work", progress=progress), step=3)
        return JobEnd(JobState.SUCCEEDED, MapBuildFinished(info=_info()))
    return body


def _info():
    return MapInfo(map_id="m", version=1, point_count=3, bounds_min_m=(0, 0, 0), bounds_max_m=(1, 1, 1))


def _terminal(events):
    return [e for e in events if e.state in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)]


def _raise(exc):
    def body(ctx):
        ctx.emit(JobEventKind.PROGRESS, ExplorationProgress(stage="a", progress=0.1), step=7)
        raise exc
    return body


@pytest.mark.parametrize("body, state, payload, error", [
    (_finished(), JobState.SUCCEEDED, MapBuildFinished, None),
    (_raise(ValueError("bad input")), JobState.FAILED, JobFailed, "ValueError: bad input"),
    (_raise(RemoteError("not_found", "no map x")), JobState.FAILED, JobFailed, "did not answer properly"),
    (_raise(Cancelled()), JobState.CANCELLED, JobCancelled, None),
    (lambda ctx: JobEnd(JobState.RUNNING, JobFailed(error="x")), JobState.FAILED, JobFailed, "must end"),
])
def test_every_way_a_body_ends_gives_exactly_one_terminal_event_with_the_step(buses, body, state, payload, error):
    a, b = buses
    got = _collect(b, "j1")
    runner = JobRunner(a, name="test")
    assert runner.submit("j1", body, KEY.format("j1")).accepted
    wait_until(lambda: _terminal(got), what="the terminal event")
    wait_until(lambda: not runner.busy(), what="the runner to be free")
    runner.close()
    assert [e.seq for e in got] == list(range(len(got)))
    (end,) = _terminal(got)
    assert end is got[-1] and end.state == state and isinstance(end.data, payload)
    assert end.step == max((e.step for e in got[:-1]), default=0)  # the step the body reached, not 0
    if error:
        assert error in end.data.error


def test_duplicate_ids_full_queue_and_unknown_cancels_are_refused_with_a_reason(buses):
    a, b = buses
    release = threading.Event()
    runner = JobRunner(a, name="test", workers=1, max_queued=1)

    def blocking(ctx):
        release.wait(5)
        ctx.check_cancelled()
        return JobEnd(JobState.SUCCEEDED, MapBuildFinished(info=_info()))

    assert runner.submit("j1", blocking, KEY.format("j1")).accepted
    wait_until(lambda: runner._queue.empty(), what="j1 to start")
    dup = runner.submit("j1", blocking, KEY.format("j1"))
    assert not dup.accepted and "already in use" in dup.reason
    assert runner.submit("j2", blocking, KEY.format("j2")).accepted  # queued behind j1
    full = runner.submit("j3", blocking, KEY.format("j3"))
    assert not full.accepted and "already queued" in full.reason
    nope = runner.cancel("zz")
    assert not nope.accepted and "no such test" in nope.reason
    with pytest.raises(ValueError):
        runner.submit("bad/id", blocking, KEY.format("x"))
    assert sorted(runner.active()) == ["j1", "j2"]
    release.set()
    wait_until(lambda: not runner.busy(), what="both jobs to end")
    runner.close()


def test_a_cancelled_queued_job_never_runs_and_ends_cancelled(buses):
    a, b = buses
    got = _collect(b, "j2")
    release, ran = threading.Event(), []
    runner = JobRunner(a, name="test", workers=1)
    runner.submit("j1", lambda ctx: (release.wait(5), JobEnd(JobState.SUCCEEDED, JobCancelled()))[1],
                  KEY.format("j1"))
    runner.submit("j2", lambda ctx: ran.append(1), KEY.format("j2"))
    assert runner.cancel("j2").accepted
    release.set()
    wait_until(lambda: _terminal(got), what="j2's end")
    runner.close()
    assert not ran and [e.state for e in got] == [JobState.CANCELLED]


def test_await_job_follows_a_job_of_another_service_to_its_end(buses):
    server, client = buses
    runner = JobRunner(server, name="build", workers=1)
    fail = {"now": False}

    def submit(req: ExplorationRequest) -> JobAccepted:
        if req.map_id == "refuse":
            return JobAccepted(job_id=req.exploration_id, accepted=False, reason="busy")
        body = _raise(ValueError("broken")) if fail["now"] else _finished()
        return runner.submit(req.exploration_id, body, KEY.format(req.exploration_id))

    server.serve("ant/test/submit", ExplorationRequest, submit)
    seen: list[JobEvent] = []
    end = await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="x1", map_id="m"), KEY.format("x1"),
                    on_event=seen.append, stall_s=5)
    assert isinstance(end.data, MapBuildFinished) and end.data.info.point_count == 3
    assert [e.kind for e in seen] == [JobEventKind.PROGRESS, JobEventKind.FINISHED]
    with pytest.raises(JobFailedError, match="refused: busy"):
        await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="x2", map_id="refuse"),
                  KEY.format("x2"), stall_s=5)
    fail["now"] = True
    with pytest.raises(JobFailedError, match="failed: ValueError: broken"):
        await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="x3", map_id="m"), KEY.format("x3"),
                  stall_s=5)
    runner.close()


def test_await_job_gives_up_on_a_silent_job(buses):
    server, client = buses
    # Accepted, then never a word: the service died after answering. Nothing ever arrives, so a short stall
    # period cannot be outrun by load; it is the whole of the test's wait.
    server.serve("ant/test/submit", ExplorationRequest,
                 lambda req: JobAccepted(job_id=req.exploration_id, accepted=True))
    with pytest.raises(JobFailedError, match="no event from job s1"):
        await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="s1", map_id="m"), KEY.format("s1"),
                  stall_s=0.1)


def test_a_cancelled_staged_job_names_the_stage_it_was_stopped_in(buses):
    a, b = buses
    got = _collect(b, "j1")
    inside = threading.Event()
    runner = JobRunner(a, name="test", workers=1)

    def staged(ctx):
        ctx.progress(ExplorationProgress(stage="exploring", progress=0.1), step=1)
        ctx.progress(ExplorationProgress(stage="touring", progress=0.3), step=2)
        inside.set()
        while True:  # a loop that checks its flag once per step, as the mapper's does
            ctx.check_cancelled()
            threading.Event().wait(0.01)

    runner.submit("j1", staged, KEY.format("j1"))
    wait_until(inside.is_set, what="the body to reach its touring stage")
    assert runner.cancel("j1").accepted
    (end,) = wait_until(lambda: _terminal(got), what="the cancelled event")
    runner.close()
    assert end.state == JobState.CANCELLED and end.step == 2
    assert end.data.stage == "touring" and end.data.message == "cancelled on request while touring"


class _RemoteBuild:
    """A job service on ``server``: submit and cancel keys, its jobs run ``body``."""

    def __init__(self, server, body):
        self.runner = JobRunner(server, name="build", workers=1)
        self.cancel_asks: list[str] = []
        server.serve("ant/test/submit", ExplorationRequest, lambda req: self.runner.submit(
            req.exploration_id, body, KEY.format(req.exploration_id)))

    def cancel(self, job_id: str) -> None:
        self.cancel_asks.append(job_id)
        self.runner.cancel(job_id)


def _slow_build(started: threading.Event):
    def body(ctx):
        for region in range(1000):  # ends only when cancelled
            ctx.progress(ExplorationProgress(stage="reconstructing", progress=0.5, region=region), step=region)
            started.set()
            ctx.check_cancelled()
            threading.Event().wait(0.01)
        return JobEnd(JobState.SUCCEEDED, MapBuildFinished(info=_info()))
    return body


def test_await_job_passes_a_cancel_on_and_waits_for_the_job_to_end_cancelled(buses):
    server, client = buses
    started, cancel = threading.Event(), threading.Event()
    remote = _RemoteBuild(server, _slow_build(started))
    threading.Thread(target=lambda: (started.wait(10), cancel.set()), daemon=True).start()
    seen: list[JobEvent] = []
    with pytest.raises(Cancelled):
        await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="c1", map_id="m"), KEY.format("c1"),
                  on_event=seen.append, stall_s=5, cancel=cancel, cancel_remote=lambda: remote.cancel("c1"))
    # Asked once, and the wait ended on the job's own cancelled event (not before): it left nothing running.
    assert remote.cancel_asks == ["c1"]
    assert seen[-1].state == JobState.CANCELLED and seen[-1].data.stage == "reconstructing"
    assert not remote.runner.busy()
    remote.runner.close()


def test_await_job_returns_a_job_that_succeeded_before_the_cancel_reached_it(buses):
    server, client = buses
    cancel = threading.Event()
    remote = _RemoteBuild(server, _finished())

    def late_cancel(job_id):  # the job is over by the time the ask arrives: refused, nothing to cancel
        wait_until(lambda: not remote.runner.busy(), what="the job to end")
        remote.cancel(job_id)

    cancel.set()  # set before the submit: the ask goes out at once
    end = await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="c2", map_id="m"), KEY.format("c2"),
                    stall_s=5, cancel=cancel, cancel_remote=lambda: late_cancel("c2"))
    assert end.state == JobState.SUCCEEDED and isinstance(end.data, MapBuildFinished)
    assert remote.cancel_asks == ["c2"]
    remote.runner.close()


def test_await_job_without_a_remote_cancel_stops_waiting_at_once(buses):
    server, client = buses
    started, cancel = threading.Event(), threading.Event()
    remote = _RemoteBuild(server, _slow_build(started))
    threading.Thread(target=lambda: (started.wait(10), cancel.set()), daemon=True).start()
    with pytest.raises(Cancelled):
        await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="c3", map_id="m"), KEY.format("c3"),
                  stall_s=5, cancel=cancel)
    assert remote.runner.busy()  # nobody told it: it runs on
    remote.runner.close()


def test_await_job_takes_a_job_silent_after_its_cancel_as_cancelled(buses):
    server, client = buses
    server.serve("ant/test/submit", ExplorationRequest,
                 lambda req: JobAccepted(job_id=req.exploration_id, accepted=True))
    cancel, asks = threading.Event(), []
    cancel.set()

    def ask():
        asks.append(1)
        raise RemoteError("unavailable", "no reconstructor")

    with pytest.raises(Cancelled):
        await_job(client, "ant/test/submit", ExplorationRequest(exploration_id="c4", map_id="m"), KEY.format("c4"),
                  stall_s=0.1, cancel=cancel, cancel_remote=ask)  # never an event: as short as the one above
    assert asks == [1]
