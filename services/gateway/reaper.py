"""Jobs whose worker died: a mission (exploration) the planner (mapper) was running when its process
went away can never finish, so the gateway ends it as failed, with the reason, instead of leaving it
``running`` forever.

The gateway watches the liveliness of the planner and the mapper. When one of their tokens drops and,
after a short grace, no instance of that service is alive, every job of that kind that has not ended
gets a final ``error`` event (seq = last + 1, state ``failed``): the record, the SSE stream (which then
ends) and the history all say why. A restarted service does not know the jobs of its previous life, so
there is nothing to resume.
"""

from __future__ import annotations

import logging
import threading

from services.gateway.events import EventHub, sse_frame
from services.gateway.records import JobKind
from services.gateway.store import EventRejected, GatewayStore
from shared import keys
from shared.bus.base import Bus, Closeable
from shared.schemas import MissionEvent, MissionEventKind, MissionState

log = logging.getLogger(__name__)

WORKERS = {"planner": JobKind.MISSION, "mapper": JobKind.EXPLORATION}
_OPEN = [MissionState.QUEUED, MissionState.RUNNING]


class JobReaper:
    """Fail the open jobs of a service that has no live instance left (see the module docstring)."""

    def __init__(self, bus: Bus, store: GatewayStore, hub: EventHub, *, grace_s: float = 0.5):
        self.bus, self.store, self.hub, self.grace_s = bus, store, hub, grace_s
        self.reaped = 0
        self._stop = threading.Event()
        self._watches: list[Closeable] = [
            bus.watch_liveliness(keys.ALIVE.pattern(service=service),
                                 lambda token, alive, s=service: self._on_token(s, token, alive))
            for service in WORKERS
        ]

    def _on_token(self, service: str, token: str, alive: bool) -> None:
        if not alive and not self._stop.is_set():
            # Off the bus's callback thread: the check below queries the bus.
            threading.Thread(target=self._check, args=(service, token), name=f"reap-{service}", daemon=True).start()

    def _check(self, service: str, token: str) -> None:
        if self._stop.wait(self.grace_s):
            return
        try:
            if self.bus.alive(keys.ALIVE.pattern(service=service), timeout_s=1.0):
                return  # another replica lives on; its jobs still report
            self.reap(service, f"the {service} stopped ({token.rsplit('/', 1)[-1]} went away) while this ran")
        except Exception:  # never let a failed check take the gateway down
            log.exception("checking open jobs of %s failed", service)

    def reap(self, service: str, reason: str) -> int:
        """End every open job of ``service``'s kind as failed with ``reason``; returns how many."""
        kind = WORKERS[service]
        n = 0
        while True:
            rows, _ = self.store.list_jobs(kind, states=_OPEN, limit=500, offset=0)
            if not rows:
                break
            for row in rows:
                event = MissionEvent(mission_id=row.id, seq=row.last_seq + 1, kind=MissionEventKind.ERROR,
                                     state=MissionState.FAILED, step=row.step, data={"error": reason})
                try:
                    stored = self.store.append_event(kind, event)
                except EventRejected:  # it ended (or moved on) in between: look again
                    stored = None
                if stored is not None:
                    n += 1
                    self.hub.publish(row.id, stored.seq, sse_frame(kind, stored))
                else:  # the worker's own event took that seq in between: mark without an event
                    self.store.mark(row.id, MissionState.FAILED, reason)
                    self.hub.notify(row.id)
        if n:
            log.warning("%d open %s(s) ended as failed: %s", n, kind.value, reason)
        self.reaped += n
        return n

    def close(self) -> None:
        self._stop.set()
        for w in self._watches:
            w.close()
        self._watches.clear()
