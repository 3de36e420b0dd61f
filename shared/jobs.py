"""One job mechanism for missions, explorations and map builds: accept, then typed events, then exactly
one terminal state (cosmicpython's commands and events; dora's typed event loop).

A service hands :class:`JobRunner` a *job body* - a plain function of a :class:`JobContext` that lives
in the service's core and works against ports - and the runner does the rest, the same way for every
kind of job:

* ``submit`` answers at once with :class:`~shared.schemas.JobAccepted` (refused, with the reason, for a
  reused id or a full queue), so no caller waits on a long synchronous query;
* the body runs on one of ``workers`` threads and reports through ``ctx.emit``/``ctx.progress``; every
  event is published on the job's own key with a gap-free ``seq`` (:class:`~shared.events.EventStream`);
* whatever happens - the body returns a :class:`JobEnd`, raises :class:`Cancelled`, a remote service
  fails, any other exception - exactly one terminal event is published, carrying the step reached;
* ``cancel`` sets the job's flag (a queued job ends cancelled without running); ``active`` lists the
  jobs a reconciler may ask about.

:func:`await_job` is the other side for a service that runs a job of another service as one step of its
own (the mapper waits for its map build): it subscribes before submitting, reports every event, and
ends on the terminal one, with a *stall* budget (no event for that long fails) instead of one long
timeout for the whole job.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from shared import keys
from shared.bus.typed import RemoteError, TypedBus
from shared.events import EventStream
from shared.schemas import EventPayload, JobAccepted, JobCancelled, JobEvent, JobEventKind, JobFailed, JobState, Message

log = logging.getLogger(__name__)

TERMINAL_STATES = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED})


class Cancelled(Exception):
    """Raised inside a job body (by :meth:`JobContext.check_cancelled`) once its cancel was requested."""


class JobFailedError(RuntimeError):
    """A job another service ran for us ended failed or cancelled (:func:`await_job`)."""


@dataclass(frozen=True)
class JobEnd:
    """How a body ended: ``state`` is SUCCEEDED or FAILED, ``payload`` the terminal event's data."""

    state: JobState
    payload: EventPayload
    step: int = 0


class JobContext:
    """What a job body sees: its id, its cancel flag, and where its events go."""

    def __init__(self, job_id: str, cancel: threading.Event, events: EventStream):
        self.job_id = job_id
        self.cancel = cancel
        self._events = events
        self.step = 0  # the last step reported; terminal events carry it
        self.stage: str | None = None  # the stage of the last staged progress reported; a cancel names it

    def emit(self, kind: JobEventKind, payload: EventPayload | None = None, *, step: int | None = None,
             images: dict[str, bytes] | None = None) -> JobEvent:
        """Publish one non-terminal event (the job is running)."""
        if step is not None:
            self.step = step
        stage = getattr(payload, "stage", None)
        if isinstance(stage, str):
            self.stage = stage
        return self._events.emit(kind, JobState.RUNNING, step=self.step, data=payload, images=images)

    def progress(self, payload: EventPayload, **kw) -> JobEvent:
        return self.emit(JobEventKind.PROGRESS, payload, **kw)

    def check_cancelled(self) -> None:
        if self.cancel.is_set():
            raise Cancelled()


JobBody = Callable[[JobContext], JobEnd]


@dataclass
class _Job:
    job_id: str
    body: JobBody
    cancel: threading.Event
    events_key: str


class JobRunner:
    """Runs submitted job bodies on ``workers`` threads from a bounded queue.

    One runner per kind of job and service; a robot's missions run one at a time (``workers=1``: a
    robot has one body). Job ids are unique among the runner's queued and running jobs.
    """

    def __init__(self, bus: TypedBus, *, name: str, workers: int = 1, max_queued: int = 16):
        if workers < 1 or max_queued < 1:
            raise ValueError("workers and max_queued must be >= 1")
        self.bus, self.name = bus, name
        self.max_queued = max_queued
        self._queue: queue.Queue[_Job | None] = queue.Queue(maxsize=max_queued)
        self._jobs: dict[str, _Job] = {}  # queued or running
        self._lock = threading.Lock()
        self._closed = False
        self._threads = [threading.Thread(target=self._work, name=f"{name}-{i}", daemon=True) for i in range(workers)]
        for t in self._threads:
            t.start()

    # --- the queryables' side ----------------------------------------------------------------------------
    def submit(self, job_id: str, body: JobBody, events_key: str) -> JobAccepted:
        """Queue ``body``; its events will be published on ``events_key`` (a concrete key)."""
        keys.validate_segment(job_id, f"{self.name} id")
        with self._lock:
            if self._closed:
                return JobAccepted(job_id=job_id, accepted=False, reason=f"the {self.name} runner is shutting down")
            if job_id in self._jobs:
                return JobAccepted(job_id=job_id, accepted=False, reason=f"{self.name} id already in use")
            job = _Job(job_id, body, threading.Event(), events_key)
            try:
                self._queue.put_nowait(job)
            except queue.Full:
                return JobAccepted(job_id=job_id, accepted=False,
                                   reason=f"{self.max_queued} {self.name} jobs already queued")
            self._jobs[job_id] = job
        return JobAccepted(job_id=job_id, accepted=True)

    def cancel(self, job_id: str) -> JobAccepted:
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None:
            return JobAccepted(job_id=job_id, accepted=False, reason=f"no such {self.name} here")
        job.cancel.set()
        return JobAccepted(job_id=job_id, accepted=True)

    def active(self) -> list[str]:
        """Ids of the queued and running jobs."""
        with self._lock:
            return list(self._jobs)

    def busy(self) -> bool:
        with self._lock:
            return bool(self._jobs)

    def close(self, timeout_s: float = 5.0) -> None:
        """Cancel every job and stop the workers (a running body stops at its next cancel check)."""
        with self._lock:
            self._closed = True
            for job in self._jobs.values():
                job.cancel.set()
        for _ in self._threads:
            try:
                self._queue.put_nowait(None)
            except queue.Full:
                break
        end = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, end - time.monotonic()))

    # --- the workers -------------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            try:
                self._run(job)
            finally:
                with self._lock:
                    self._jobs.pop(job.job_id, None)

    def _run(self, job: _Job) -> None:
        events = EventStream(self.bus, job.events_key, job.job_id)
        ctx = JobContext(job.job_id, job.cancel, events)
        try:
            ctx.check_cancelled()
            end = job.body(ctx)
            if end.state not in (JobState.SUCCEEDED, JobState.FAILED):
                raise ValueError(f"a job body must end succeeded or failed, not {end.state}")
            events.emit(JobEventKind.FINISHED, end.state, step=max(end.step, ctx.step), data=end.payload)
        except Cancelled:
            message = f"cancelled on request while {ctx.stage}" if ctx.stage else "cancelled on request"
            events.emit(JobEventKind.FINISHED, JobState.CANCELLED, step=ctx.step,
                        data=JobCancelled(message=message, stage=ctx.stage))
        except RemoteError as exc:
            log.warning("%s %s failed: %s", self.name, job.job_id, exc)
            events.emit(JobEventKind.ERROR, JobState.FAILED, step=ctx.step,
                        data=JobFailed(error=f"a service did not answer properly: {exc}"))
        except Exception as exc:  # a failed job ends with its cause, never silently
            log.exception("%s %s failed", self.name, job.job_id)
            events.emit(JobEventKind.ERROR, JobState.FAILED, step=ctx.step,
                        data=JobFailed(error=f"{type(exc).__name__}: {exc}"))


def await_job(bus: TypedBus, submit_key: str, request: Message, events_key: str, *,
              on_event: Callable[[JobEvent], None] | None = None, stall_s: float = 300.0,
              submit_timeout_s: float = 10.0, cancel: threading.Event | None = None,
              cancel_remote: Callable[[], None] | None = None) -> JobEvent:
    """Submit ``request`` on ``submit_key`` and follow the job's events on ``events_key`` to its end.

    Returns the terminal event when the job succeeded; raises :class:`JobFailedError` when it failed or
    was cancelled, when it was refused, or when no event arrived for ``stall_s`` (the job's service
    died).

    ``cancel`` set by the caller (checked after every event, and at least every 0.25 s) stops the wait:

    * with ``cancel_remote`` (a call that asks the job's service to cancel the job), that is called once
      and the job is still followed to its end, so that the caller knows what the job left behind: it
      raises :class:`Cancelled` when the job ended cancelled (or went silent for ``stall_s`` after the
      ask: its service is gone), and returns the terminal event as usual when the job had succeeded
      before the cancel reached it (its result is whole);
    * without, the wait ends at once with :class:`Cancelled` and the job runs on.
    """
    inbox: queue.Queue[JobEvent] = queue.Queue()
    # Subscribe first: an event published between the reply and the subscription would be lost.
    sub = bus.subscribe(events_key, JobEvent, lambda _key, ev: inbox.put(ev))
    poll_s = min(stall_s, 0.25 if cancel is not None else 1.0)
    try:
        reply = bus.request(submit_key, request, JobAccepted, timeout_s=submit_timeout_s)
        if not reply.accepted:
            raise JobFailedError(f"refused: {reply.reason or 'no reason given'}")
        seen, last_s, asked = -1, time.monotonic(), False
        while True:
            if cancel is not None and cancel.is_set() and not asked:
                if cancel_remote is None:
                    raise Cancelled()
                asked = True
                try:
                    cancel_remote()
                except Exception as exc:  # noqa: BLE001 - followed to its end either way; a dead service stalls
                    log.warning("could not ask to cancel job %s: %s", reply.job_id, exc)
            try:
                ev = inbox.get(timeout=poll_s)
            except queue.Empty:
                if time.monotonic() - last_s > stall_s:
                    if asked:
                        log.warning("job %s sent nothing for %.3g s after its cancel; taken as cancelled",
                                    reply.job_id, stall_s)
                        raise Cancelled() from None
                    raise JobFailedError(f"no event from job {reply.job_id} for {stall_s:.3g} s") from None
                continue
            last_s = time.monotonic()
            if ev.job_id != reply.job_id or ev.seq <= seen:
                continue  # another job's, or a replay of one already handled
            seen = ev.seq
            if on_event is not None:
                on_event(ev)
            if ev.state in TERMINAL_STATES:
                if ev.state == JobState.CANCELLED and asked:
                    raise Cancelled()
                if ev.state != JobState.SUCCEEDED:
                    why = getattr(ev.data, "error", "") or getattr(ev.data, "message", "") or ev.state.value
                    raise JobFailedError(f"job {reply.job_id} {ev.state.value}: {why}")
                return ev
    finally:
        sub.close()
