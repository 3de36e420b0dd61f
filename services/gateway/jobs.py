"""What the job routers (missions, explorations) and the robot router share: starting and cancelling a
job, following its events, serving its pictures, and the scene-switch guard. The routers import this,
never each other.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from fastapi import Request
from fastapi.responses import Response, StreamingResponse

from services.gateway.errors import GatewayError, remote_detail, remote_status
from services.gateway.events import parse_last_event_id, sse_stream
from services.gateway.reaper import find_owner
from services.gateway.records import JobKind
from services.gateway.store import GatewayStore, JobRow
from shared.bus.typed import RemoteError
from shared.schemas import ErrorCode, JobAccepted, JobState

OPEN_STATES = [JobState.QUEUED, JobState.RUNNING]


def open_jobs(store: GatewayStore, limit: int = 5) -> list[str]:
    """Descriptions of up to ``limit`` missions and explorations not yet ended."""
    out: list[str] = []
    for kind in (JobKind.MISSION, JobKind.EXPLORATION):
        rows, total = store.list_jobs(kind, states=OPEN_STATES, limit=limit)
        out += [f"{kind.value} {r.id} ({r.state.value})" for r in rows]
        if total > len(rows):
            out.append(f"{total - len(rows)} more {kind.value}(s)")
    return out


def scene_lock(request: Request) -> threading.Lock:
    return request.app.state.scene_lock


def refuse_while_switching(request: Request, what: str) -> None:
    """For job submissions: 409 while ``POST /robot/scene`` is loading a scene.

    Called after the job's row exists, so that either the switch sees the job or the job sees the
    switch, whatever the interleaving."""
    if scene_lock(request).locked():
        raise GatewayError(f"the robot is switching scenes: submit the {what} once it has finished", 409)


def start_job(store, kind: JobKind, job_id: str, request_json: dict, http_request: Request, noun: str,
              service: str, send: Callable[[], JobAccepted]) -> None:
    """Create the job's row, then hand the job to its service (``send``).

    The row exists before the service hears of the job, so its first event has a home; it is
    removed again when the job cannot start (a scene switch under way, the service absent or
    refusing), so a refused request leaves nothing behind. Once accepted, the job records its owner
    (the worker instance and incarnation) for the reaper's reconciliation.
    """
    store.create_job(kind, job_id, request_json)
    try:
        refuse_while_switching(http_request, noun)
        try:
            reply = send()
        except RemoteError as exc:
            raise GatewayError(remote_detail(exc, f"the {service} refused the {noun}"), remote_status(exc)) from None
        if not reply.accepted:
            raise GatewayError(f"the {service} refused the {noun}: {reply.reason or 'no reason given'}", 409)
    except BaseException:
        store.delete_job(job_id)
        raise
    settings = http_request.app.state.settings
    store.set_owner(job_id, find_owner(http_request.app.state.bus, service, reply.instance,
                                       timeout_s=settings.status_timeout_s))


def cancel_job(store: GatewayStore, kind: JobKind, job_id: str, http_request: Request, service: str,
               ask: Callable[[], list[JobAccepted | RemoteError]]) -> JobRow:
    """Ask the job's workers to cancel it (``ask``: every replica's answer); returns its row afterwards.

    404 for an unknown job, 409 for one that has ended (terminal states are final: a rejected cancel
    changes nothing). The job's own ``cancelled`` event follows on its stream. A job no live worker runs
    (an orphan: its worker died or restarted, none answered, or each said it has no such job) can never
    finish, so it is cancelled here at once, as asked."""
    row = store.get_job(job_id, kind)
    if row is None:
        raise GatewayError(f"no {kind.value} {job_id!r}", 404)
    if row.state == JobState.CANCELLED:
        raise GatewayError(f"{kind.value} {job_id!r} is already cancelled", 409)
    if row.terminal:
        raise GatewayError(f"{kind.value} {job_id!r} has already ended ({row.state.value})", 409)
    answers = ask()
    if not any(isinstance(a, JobAccepted) and a.accepted for a in answers):
        failures = [a for a in answers if isinstance(a, RemoteError) and a.code != ErrorCode.NOT_FOUND]
        if failures and len(failures) == len(answers):
            raise GatewayError(remote_detail(failures[0], "cannot cancel"), remote_status(failures[0]))
        why = f"no {service} answered" if not answers else f"no {service} runs it any more"
        http_request.app.state.reaper.fail(kind, job_id, f"cancelled on request; {why}", state=JobState.CANCELLED)
    return store.get_job(job_id, kind) or row


def events_response(kind: JobKind, job_id: str, store, hub, settings, last_event_id: str | None,
                    after: int | None) -> StreamingResponse:
    if store.get_job(job_id, kind) is None:
        raise GatewayError(f"no {kind.value} {job_id!r}", 404)
    try:
        start = parse_last_event_id(last_event_id, after)
    except ValueError as exc:
        raise GatewayError(str(exc), 400) from None
    stream = sse_stream(store, hub, kind, job_id, start, keepalive_s=settings.sse_keepalive_s,
                        batch=settings.sse_batch)
    # no-transform and X-Accel-Buffering: proxies must pass events through as they come.
    return StreamingResponse(stream, media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache, no-transform", "X-Accel-Buffering": "no"})


def image_response(store, job_id: str, seq: int, name: str) -> Response:
    jpeg = store.image(job_id, seq, name)
    if jpeg is None:
        raise GatewayError(f"no image {name!r} at event {seq} of {job_id!r}", 404)
    # An event's image never changes once stored.
    return Response(jpeg, media_type="image/jpeg", headers={"Cache-Control": "public, max-age=31536000, immutable"})
