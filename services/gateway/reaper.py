"""Jobs whose worker is gone: a mission (exploration) whose planner (mapper) died, or restarted and so
forgot it, can never finish; the gateway ends it as failed, with the reason, instead of leaving it
``running`` forever (a running job also blocks ``POST /robot/scene``).

Each job records its *owner* when it is accepted: the worker instance and the ``started_s`` of its
incarnation (from its ``info`` queryable), so a worker restarted under the same instance name is told
apart from the one that took the job. :meth:`JobReaper.reconcile` compares every job that has not
ended with the live workers:

* the owner's liveliness token is gone and its ``info`` does not answer, or its ``info`` answers with
  another ``started_s``: orphan;
* a job whose owner is unknown (accepted by a worker that cannot be identified) is an orphan only
  when no instance of its service is alive at all.

An orphan must be seen twice, ``confirm_s`` apart, before it is failed (a worker that is only slow to
be seen after a gateway start is not one). Reconciliation runs at start, every ``interval_s``, and
after a worker's liveliness token drops; the failure is a final ``error`` event (seq = last + 1,
state ``failed``) so the record, the SSE stream and the history all say why.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from services.gateway.events import EventHub, sse_frame
from services.gateway.records import JobKind
from services.gateway.store import EventRejected, GatewayStore, JobRow
from shared import keys
from shared.bus.base import Closeable
from shared.bus.typed import TypedBus
from shared.clients import ServicesClient
from shared.schemas import JobCancelled, JobFailed, JobEvent, JobEventKind, JobState

log = logging.getLogger(__name__)

WORKERS = {"planner": JobKind.MISSION, "mapper": JobKind.EXPLORATION}
SERVICE_OF = {kind: service for service, kind in WORKERS.items()}
_OPEN = [JobState.QUEUED, JobState.RUNNING]


def live_workers(bus: TypedBus, service: str, timeout_s: float) -> tuple[set[str], dict[str, float]]:
    """(instances whose liveliness token is up, instance -> started_s of those whose info answered)."""
    client = ServicesClient(bus, timeout_s=timeout_s)
    alive = {instance for _, instance in client.alive(service)}
    started = {r.instance: r.started_s for r in client.infos(service)}
    return alive, started


def find_owner(bus: TypedBus, service: str, instance: str = "", timeout_s: float = 2.0) -> dict[str, Any] | None:
    """The worker that accepted a job: ``instance`` when the reply named it, else the one live
    instance of ``service`` (None when there are several, or none answers)."""
    try:
        _, started = live_workers(bus, service, timeout_s)
    except Exception:  # the job is accepted either way; an unknown owner is reconciled coarsely
        log.exception("cannot identify the %s that accepted a job", service)
        return None
    if instance:
        return {"service": service, "instance": instance, "started_s": started.get(instance)}
    if len(started) == 1:
        ((name, started_s),) = started.items()
        return {"service": service, "instance": name, "started_s": started_s}
    return None


def orphan_reason(owner: dict[str, Any] | None, service: str, alive: set[str], started: dict[str, float], *,
                  dropped: bool = False) -> str | None:
    """Why a job of ``service`` can never finish, or None while it still can. A job without a known
    owner is judged only after a worker's token was seen to drop (``dropped``): a worker that
    announces no liveliness at all (a test double) is not taken for a dead one."""
    if not owner or not owner.get("instance"):
        return f"no {service} is running any more" if dropped and not alive else None
    name = owner["instance"]
    was, now = owner.get("started_s"), started.get(name)
    # Gone only when neither its liveliness token nor its info answers: a liveliness query of a loaded
    # gateway can end without the reply of a worker that is busy and well (seen: a ROS 2 demo's
    # exploration failed mid-tour as "went away", twice 1 s apart, while its mapper kept recording).
    if name not in alive and now is None:
        return f"the {service} {name} that ran it went away"
    if was is not None and now is not None and abs(now - was) > 1e-3:
        at = time.strftime("%H:%M:%S", time.gmtime(now))
        return f"the {service} {name} that ran it restarted (at {at} UTC) and lost it"
    return None


class JobReaper:
    """Reconcile the jobs that have not ended with the live workers (see the module docstring)."""

    def __init__(self, bus: TypedBus, store: GatewayStore, hub: EventHub, *, grace_s: float = 0.5,
                 interval_s: float = 5.0, startup_s: float = 2.0, confirm_s: float = 1.0, timeout_s: float = 2.0,
                 min_age_s: float = 2.0):
        self.bus, self.store, self.hub = bus, store, hub
        self.grace_s, self.interval_s, self.confirm_s, self.timeout_s = grace_s, interval_s, confirm_s, timeout_s
        self.min_age_s = min_age_s
        self.reaped = 0
        self.rounds = 0
        self._stop = threading.Event()
        self._lock = threading.Lock()  # one reconciliation at a time
        self._watches: list[Closeable] = [
            bus.raw.watch_liveliness(keys.ALIVE.pattern(service=service),
                                     lambda token, alive, s=service: self._on_token(s, token, alive))
            for service in WORKERS
        ]
        self._thread = threading.Thread(target=self._loop, args=(startup_s,), name="reconcile", daemon=True)
        self._thread.start()

    def _on_token(self, service: str, token: str, alive: bool) -> None:
        if not alive and not self._stop.is_set():
            # Off the bus's callback thread: reconciling queries the bus.
            threading.Thread(target=self._after_drop, args=(service, token), name=f"reap-{service}",
                             daemon=True).start()

    def _after_drop(self, service: str, token: str) -> None:
        if self._stop.wait(self.grace_s):
            return
        try:
            self.reconcile(services=[service], confirm_s=self.grace_s, dropped=True)
        except Exception:  # never let a failed check take the gateway down
            log.exception("reconciling the jobs of %s after %s went away failed", service, token)

    def _loop(self, startup_s: float) -> None:
        wait = startup_s
        while not self._stop.wait(wait):
            try:
                self.reconcile()
            except Exception:
                log.exception("reconciling open jobs failed")
            wait = self.interval_s

    def _orphans(self, service: str, dropped: bool) -> dict[str, tuple[JobRow, str]]:
        kind = WORKERS[service]
        alive, started = live_workers(self.bus, service, self.timeout_s)
        now = time.time()
        out: dict[str, tuple[JobRow, str]] = {}
        offset = 0
        while True:
            rows, _ = self.store.list_jobs(kind, states=_OPEN, limit=500, offset=offset)
            for row in rows:
                if now - row.created_s < self.min_age_s:
                    continue  # just submitted: its owner is being recorded
                reason = orphan_reason(row.summary.get("owner"), service, alive, started, dropped=dropped)
                if reason:
                    out[row.id] = (row, reason)
            if len(rows) < 500:
                return out
            offset += 500

    def reconcile(self, services: list[str] | None = None, confirm_s: float | None = None,
                  dropped: bool = False) -> int:
        """Fail the jobs whose worker is gone, seen so twice ``confirm_s`` apart; returns how many."""
        with self._lock:
            n = 0
            for service in services or list(WORKERS):
                first = self._orphans(service, dropped)
                if not first or self._stop.wait(self.confirm_s if confirm_s is None else confirm_s):
                    continue
                second = self._orphans(service, dropped)
                for job_id, (row, reason) in second.items():
                    if job_id in first:
                        n += self.fail(WORKERS[service], job_id, f"{reason} while this ran")
            self.rounds += 1
            if n:
                log.warning("%d open job(s) ended as failed: their workers are gone", n)
            self.reaped += n
            return n

    def fail(self, kind: JobKind, job_id: str, reason: str, state: JobState = JobState.FAILED) -> int:
        """End one open job with ``reason`` (a final event when its seq is free); 1 when it ended here."""
        row = self.store.get_job(job_id, kind)
        if row is None or row.terminal:
            return 0
        ev_kind = JobEventKind.ERROR if state == JobState.FAILED else JobEventKind.FINISHED
        data = JobFailed(error=reason) if state == JobState.FAILED else JobCancelled(message=reason)
        event = JobEvent(job_id=row.id, seq=row.last_seq + 1, kind=ev_kind, state=state, step=row.step,
                             data=data)
        try:
            stored = self.store.append_event(kind, event)
        except EventRejected:  # it ended (or moved on) in between: look again
            stored = None
        if stored is not None:
            self.hub.publish(row.id, stored.seq, sse_frame(kind, stored))
            return 1
        row = self.store.get_job(job_id, kind)
        if row is None or row.terminal:
            return 0
        self.store.mark(row.id, state, reason if state == JobState.FAILED else None)
        self.hub.notify(row.id)
        return 1

    def close(self) -> None:
        self._stop.set()
        for w in self._watches:
            w.close()
        self._watches.clear()
        self._thread.join(self.timeout_s * 2 + self.confirm_s + 1)
