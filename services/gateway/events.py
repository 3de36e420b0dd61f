"""Events: from the bus into SQLite, and from SQLite out to Server-Sent Events streams.

:class:`EventIngest` subscribes to every mission's and exploration's events of this robot and stores
each one (whether or not anybody listens), then wakes the streams of that job through
:class:`EventHub`. :func:`sse_stream` replays a job's stored events after ``Last-Event-ID`` and then
follows it live until the job ends: the database is the single source, so a stream that resumes
misses nothing and never sees an event twice.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import Counter, OrderedDict
from collections.abc import AsyncIterator

from starlette.concurrency import run_in_threadpool

from services.gateway.records import TERMINAL, JobKind
from services.gateway.store import EventRejected, GatewayStore, StoredEvent, image_url
from shared import keys
from shared.bus.base import Closeable
from shared.bus.typed import TypedBus
from shared.schemas import JobEvent

log = logging.getLogger(__name__)


class EventHub:
    """Fan-out of stored events to the SSE streams, on the event loop.

    The ingest encodes each stored event as an SSE frame once and :meth:`publish`-es it (from any
    thread); the hub keeps the newest frames of the most recently active jobs and wakes that job's
    streams, which then send the shared frames without touching the database. A stream that is
    behind what the hub kept (a replay, or a seq that arrived out of order) reads the database.

    Each job has one ``asyncio.Event`` that is swapped for a fresh one on every notification, so a
    waiter that took the event before reading cannot miss a notification that lands in between.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, *, tail_frames: int = 64, tail_jobs: int = 64):
        self._loop = loop
        self._events: dict[str, asyncio.Event] = {}
        # job -> {seq: frame}; jobs in least-recently-published order, both bounded.
        self._tails: OrderedDict[str, dict[int, str]] = OrderedDict()
        self.tail_frames, self.tail_jobs = tail_frames, tail_jobs
        self._closed = False

    def token(self, job_id: str) -> asyncio.Event:
        ev = self._events.get(job_id)
        if ev is None:
            ev = self._events[job_id] = asyncio.Event()
        return ev

    def _wake(self, job_id: str) -> None:
        ev = self._events.pop(job_id, None)
        if ev is not None:
            ev.set()

    def _keep(self, job_id: str, seq: int, frame: str) -> None:
        tail = self._tails.get(job_id)
        if tail is None:
            tail = self._tails[job_id] = {}
            while len(self._tails) > self.tail_jobs:
                self._tails.popitem(last=False)
        else:
            self._tails.move_to_end(job_id)
        tail[seq] = frame
        while len(tail) > self.tail_frames:
            del tail[min(tail)]
        self._wake(job_id)

    def _call(self, fn, *args) -> None:
        if self._closed:
            return
        try:
            self._loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # the loop is closing: nobody is left to wake
            pass

    def notify(self, job_id: str) -> None:
        """The job changed (an event with no frame to share, or a state set by the gateway)."""
        self._call(self._wake, job_id)

    def publish(self, job_id: str, seq: int, frame: str) -> None:
        """A new event of ``job_id`` was stored; ``frame`` is its encoded SSE message."""
        self._call(self._keep, job_id, seq, frame)

    def frames_after(self, job_id: str, after_seq: int, limit: int) -> list[tuple[int, str]]:
        """The kept frames after ``after_seq`` while their seqs run on without a gap (loop thread only)."""
        tail = self._tails.get(job_id)
        out: list[tuple[int, str]] = []
        if tail is None:
            return out
        seq = after_seq + 1
        while len(out) < limit and (frame := tail.get(seq)) is not None:
            out.append((seq, frame))
            seq += 1
        return out

    def close(self) -> None:
        self._closed = True
        for job_id in list(self._events):
            self._wake(job_id)


class EventIngest:
    """Subscriptions that persist every event of ``robot``'s missions and explorations.

    Nothing an event claims is taken on trust: the job id is the one of the key it came on (an event
    on mission A's key naming mission B is refused), and the store refuses an event for a job it
    does not hold, for a job that has ended, with a seq that does not increase, or whose kind
    contradicts its state. Refusals are counted by reason (``rejected``) and logged.
    """

    _KEYS = {JobKind.MISSION: keys.MISSION_EVENTS, JobKind.EXPLORATION: keys.EXPLORATION_EVENTS}
    _ID_PART = {JobKind.MISSION: "mission", JobKind.EXPLORATION: "exploration"}

    def __init__(self, bus: TypedBus, store: GatewayStore, hub: EventHub, robot: str):
        self.store, self.hub = store, hub
        self.stored = 0
        self.duplicates = 0
        self.rejected: Counter[str] = Counter()
        self._subs: list[Closeable] = [
            # history: events published while this gateway was down come back from the
            # publishers' caches; the store ignores the ones it already has.
            bus.subscribe(key.pattern(robot=robot), JobEvent,
                          lambda k, ev, kind=kind: self._on_event(kind, ev, k), history=True)
            for kind, key in self._KEYS.items()
        ]

    def _reject(self, kind: JobKind, key: str, event: JobEvent, why: str, detail: str) -> None:
        self.rejected[why] += 1
        log.warning("rejected %s event on %s (seq %d, %s/%s): %s", kind.value, key, event.seq, event.kind.value,
                    event.state.value, detail)

    def _on_event(self, kind: JobKind, event: JobEvent, key: str | None = None) -> None:
        if key is not None:
            parts = self._KEYS[kind].parse(key)
            job_id = parts[self._ID_PART[kind]] if parts else None
            if job_id != event.job_id:
                self._reject(kind, key, event, "id_mismatch",
                             f"the event names {event.job_id!r}, its key {job_id!r}")
                return
        try:
            stored = self.store.append_event(kind, event)
        except EventRejected as exc:
            self._reject(kind, key or event.job_id, event, _why(exc.reason), exc.reason)
            return
        if stored is not None:
            self.stored += 1
            # Encoded once here, sent by every stream of the job.
            self.hub.publish(event.job_id, stored.seq, sse_frame(kind, stored))
        else:
            self.duplicates += 1

    def close(self) -> None:
        for s in self._subs:
            s.close()
        self._subs.clear()


def _why(reason: str) -> str:
    """A short counter name for a rejection reason."""
    for word, name in (("no ", "unknown_job"), ("already ended", "terminal"), ("does not increase", "replayed"),
                       ("goes back", "step_back"), ("cannot be", "kind_state")):
        if word in reason:
            return name
    return "other"


def event_json(kind: JobKind, ev: StoredEvent) -> dict:
    return {"mission_id": ev.job_id, "seq": ev.seq, "kind": ev.kind, "state": ev.state.value, "step": ev.step,
            "timestamp_s": ev.timestamp_s, "data": ev.data,
            "images": {n: image_url(kind, ev.job_id, ev.seq, n) for n in ev.image_names}}


def event_json_text(kind: JobKind, ev: StoredEvent) -> str:
    """:func:`event_json` as compact JSON, splicing in the stored ``data`` text instead of re-encoding it."""
    head = json.dumps({"mission_id": ev.job_id, "seq": ev.seq, "kind": ev.kind, "state": ev.state.value,
                       "step": ev.step, "timestamp_s": ev.timestamp_s}, separators=(",", ":"))
    images = json.dumps({n: image_url(kind, ev.job_id, ev.seq, n) for n in ev.image_names}, separators=(",", ":"))
    return f'{head[:-1]},"data":{ev.data_json},"images":{images}}}'


def sse_frame(kind: JobKind, ev: StoredEvent) -> str:
    """One SSE message; the id lets EventSource resume with Last-Event-ID after a reconnect."""
    return f"id: {ev.seq}\nevent: {ev.kind}\ndata: {event_json_text(kind, ev)}\n\n"


def parse_last_event_id(header: str | None, query: int | None) -> int:
    """The seq a stream resumes after: ``Last-Event-ID`` wins over ``?after=``; -1 = from the start."""
    if header is not None and header.strip():
        try:
            return max(-1, int(header.strip()))
        except ValueError:
            raise ValueError(f"Last-Event-ID must be an integer seq, got {header!r}") from None
    return -1 if query is None else max(-1, query)


async def sse_stream(store: GatewayStore, hub: EventHub, kind: JobKind, job_id: str, after_seq: int, *,
                     keepalive_s: float, batch: int, retry_ms: int = 2000) -> AsyncIterator[str]:
    """Stored events after ``after_seq``, then live ones; ends with an ``end`` event once the job has
    finished and everything was sent. Live events come from the hub's shared frames; the database
    only serves what the hub does not hold."""
    last = after_seq
    yield f"retry: {retry_ms}\n\n"
    while True:
        wake = hub.token(job_id)  # taken before the reads: see EventHub
        # SQLite reads run in the threadpool: the event loop serves every other stream meanwhile.
        progress = await run_in_threadpool(store.job_progress, job_id)
        if progress is None:
            return
        state, last_seq = progress
        if last < last_seq:
            frames = hub.frames_after(job_id, last, batch)
            if frames:
                for seq, frame in frames:
                    last = seq
                    yield frame
                continue
            events = await run_in_threadpool(store.events, job_id, last, batch)
            for ev in events:
                last = ev.seq
                yield sse_frame(kind, ev)
            if events:
                continue
        if state in TERMINAL:
            # Everything stored was sent (last_seq counts events, a gateway-set state adds none).
            yield f"event: end\ndata: {json.dumps({'state': state.value, 'last_seq': last_seq})}\n\n"
            return
        try:
            await asyncio.wait_for(wake.wait(), keepalive_s)
        except TimeoutError:
            yield ": keepalive\n\n"
