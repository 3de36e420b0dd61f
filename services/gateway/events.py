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
from collections.abc import AsyncIterator

from services.gateway.records import TERMINAL, JobKind
from services.gateway.store import GatewayStore, StoredEvent, image_url
from shared import keys
from shared.bus.base import Closeable
from shared.bus.typed import TypedBus
from shared.schemas import MissionEvent

log = logging.getLogger(__name__)


class EventHub:
    """Wakes the SSE streams of a job when a new event of it is stored.

    Lives on the event loop; :meth:`notify` may be called from any thread. Each job has one
    ``asyncio.Event`` that is swapped for a fresh one on every notification, so a waiter that took the
    event before reading the database cannot miss a notification that lands in between.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop):
        self._loop = loop
        self._events: dict[str, asyncio.Event] = {}
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

    def notify(self, job_id: str) -> None:
        if self._closed:
            return
        try:
            self._loop.call_soon_threadsafe(self._wake, job_id)
        except RuntimeError:  # the loop is closing: nobody is left to wake
            pass

    def close(self) -> None:
        self._closed = True
        for job_id in list(self._events):
            self._wake(job_id)


class EventIngest:
    """Subscriptions that persist every event of ``robot``'s missions and explorations."""

    def __init__(self, bus: TypedBus, store: GatewayStore, hub: EventHub, robot: str):
        self.store, self.hub = store, hub
        self.stored = 0
        self.duplicates = 0
        self._subs: list[Closeable] = [
            # history: events published while this gateway was down come back from the
            # publishers' caches; the store ignores the ones it already has.
            bus.subscribe(keys.MISSION_EVENTS.pattern(robot=robot), MissionEvent,
                          lambda _k, ev: self._on_event(JobKind.MISSION, ev), history=True),
            bus.subscribe(keys.EXPLORATION_EVENTS.pattern(robot=robot), MissionEvent,
                          lambda _k, ev: self._on_event(JobKind.EXPLORATION, ev), history=True),
        ]

    def _on_event(self, kind: JobKind, event: MissionEvent) -> None:
        if self.store.append_event(kind, event):
            self.stored += 1
            self.hub.notify(event.mission_id)
        else:
            self.duplicates += 1

    def close(self) -> None:
        for s in self._subs:
            s.close()
        self._subs.clear()


def event_json(kind: JobKind, ev: StoredEvent) -> dict:
    return {"mission_id": ev.job_id, "seq": ev.seq, "kind": ev.kind, "state": ev.state.value, "step": ev.step,
            "timestamp_s": ev.timestamp_s, "data": ev.data,
            "images": {n: image_url(kind, ev.job_id, ev.seq, n) for n in ev.image_names}}


def _frame(kind: JobKind, ev: StoredEvent) -> str:
    # One SSE message; the id lets EventSource resume with Last-Event-ID after a reconnect.
    return f"id: {ev.seq}\nevent: {ev.kind}\ndata: {json.dumps(event_json(kind, ev), separators=(',', ':'))}\n\n"


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
    finished and everything was sent."""
    last = after_seq
    yield f"retry: {retry_ms}\n\n"
    while True:
        wake = hub.token(job_id)  # taken before the read: see EventHub
        events = store.events(job_id, last, batch)
        for ev in events:
            last = ev.seq
            yield _frame(kind, ev)
        if len(events) == batch:
            continue
        progress = store.job_progress(job_id)
        if progress is None:
            return
        state, last_seq = progress
        if state in TERMINAL:
            if last >= last_seq:
                yield f"event: end\ndata: {json.dumps({'state': state.value, 'last_seq': last_seq})}\n\n"
                return
            continue  # the final events were stored between the two reads
        try:
            await asyncio.wait_for(wake.wait(), keepalive_s)
        except TimeoutError:
            yield ": keepalive\n\n"
