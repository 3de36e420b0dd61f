"""Missions: submit, list, inspect, cancel, follow live (SSE) and fetch their pictures."""

from __future__ import annotations

import logging
import uuid
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from services.gateway.cache import record_response
from services.gateway.deps import Authorized, BusDep, CacheDep, HubDep, SettingsDep, StoreDep
from services.gateway.errors import GatewayError, remote_detail, remote_status
from services.gateway.events import event_json
from services.gateway.jobs import cancel_job, events_response, image_response, start_job
from services.gateway.params import (
    IMAGE_DOC,
    RECORD_DOC,
    SEGMENT,
    SSE_DOC,
    After,
    IfNoneMatch,
    ImageName,
    LastEventId,
    MissionId,
    Seq,
)
from services.gateway.records import (
    EventRecord,
    JobCreated,
    JobKind,
    MissionPage,
    MissionRecord,
    MissionSummary,
    outcome_of,
)
from services.gateway.store import JobRow
from shared.bus.typed import NoReplyError, RemoteError
from shared.clients import MapClient, PlannerClient, RobotClient
from shared.schemas import ErrorCode, Instruction, JobState, MissionOptions, MissionRequest

log = logging.getLogger(__name__)
router = APIRouter(prefix="/missions", tags=["missions"])



class MissionCreate(BaseModel):
    """``POST /missions``: what to do, on which map, how."""

    model_config = ConfigDict(extra="forbid")

    instruction: Instruction
    map_id: str = Field(pattern=SEGMENT, description="a map listed by GET /maps")
    options: MissionOptions = Field(default_factory=MissionOptions)


def _links(job_id: str) -> tuple[str, str]:
    return f"/missions/{job_id}", f"/missions/{job_id}/events"


def mission_record(row: JobRow) -> MissionRecord:
    url, events_url = _links(row.id)
    s = row.summary
    req = row.request
    return MissionRecord(
        id=row.id, kind=JobKind.MISSION, state=row.state, step=row.step, last_seq=row.last_seq,
        created_s=row.created_s, updated_s=row.updated_s, started_s=s.get("started_s"),
        finished_s=s.get("finished_s"), error=s.get("error"), message=s.get("message"), images=s.get("images", {}),
        url=url, events_url=events_url, instruction=req.get("instruction", ""), map_id=req.get("map_id", ""),
        options=req.get("options", {}), pose=s.get("pose"), trajectory=s.get("trajectory", []),
        candidates=s.get("candidates", []), decisions=s.get("decisions", []), metrics=s.get("metrics"),
        outcome=outcome_of(row.state, s.get("outcome")), success=s.get("success"),
        prompt_tokens=s.get("prompt_tokens", 0), completion_tokens=s.get("completion_tokens", 0),
        cost_usd=s.get("cost_usd", 0.0))


def _summary(row: JobRow) -> MissionSummary:
    return MissionSummary(id=row.id, state=row.state, outcome=outcome_of(row.state, row.summary.get("outcome")),
                          success=row.summary.get("success"), step=row.step, instruction=row.request.get("instruction", ""),
                          map_id=row.request.get("map_id", ""), created_s=row.created_s, updated_s=row.updated_s,
                          url=f"/missions/{row.id}")


def _get(store, job_id: str) -> JobRow:
    row = store.get_job(job_id, JobKind.MISSION)
    if row is None:
        raise GatewayError(f"no mission {job_id!r}", 404)
    return row


def check_poses(bus, settings, options: MissionOptions) -> None:
    """A start pose or a goal must lie on (or near) walkable ground: robot-io would otherwise snap
    (1e6, 1e6) to some corner where the robot cannot move. 422 with the distance when it does not."""
    start = options.start_pose.position_m if options.start_pose is not None else None
    goal = options.goal_m
    if start is None and goal is None:
        return
    try:
        reply = RobotClient(bus, settings.robot, timeout_s=settings.request_timeout_s).geodesic(start or goal,
                                                                                               goal or start)
    except NoReplyError:
        # No robot-io serves the scene: nothing to check against here; the mission itself then fails
        # with that reason when it starts.
        log.warning("no robot-io answered: start_pose/goal_m not checked against the scene")
        return
    except RemoteError as exc:
        raise GatewayError(remote_detail(exc, "cannot check start_pose/goal_m against the scene"),
                           remote_status(exc)) from None
    tol = settings.pose_tolerance_m
    for name, value, off in (("options.start_pose", start, reply.start_off_m), ("options.goal_m", goal, reply.goal_off_m)):
        if value is not None and off is not None and off > tol:
            raise GatewayError(f"{name} {tuple(round(v, 3) for v in value)} is {off:.2f} m from walkable ground "
                               f"(tolerance {tol:.2f} m)", 422)


@router.post("", response_model=JobCreated, status_code=status.HTTP_202_ACCEPTED, dependencies=[Authorized],
             responses={401: {}, 409: {}, 413: {}, 422: {}, 503: {}})
def submit(body: MissionCreate, request: Request, bus: BusDep, store: StoreDep, settings: SettingsDep,
           response: Response) -> JobCreated:
    """Start a navigation mission; follow it at ``url`` (poll) or ``events_url`` (SSE)."""
    if len(body.instruction) > settings.max_instruction_chars:
        raise GatewayError(f"instruction longer than {settings.max_instruction_chars} characters", 422)
    if settings.validate_map:
        try:
            MapClient(bus, timeout_s=settings.request_timeout_s).info(body.map_id)
        except RemoteError as exc:
            if exc.code == ErrorCode.NOT_FOUND:
                raise GatewayError(f"unknown map {body.map_id!r} (see GET /maps)", 422) from None
            raise GatewayError(remote_detail(exc, "cannot check the map"), remote_status(exc)) from None
    check_poses(bus, settings, body.options)
    job_id = f"m-{uuid.uuid4().hex[:16]}"
    start_job(store, JobKind.MISSION, job_id, body.model_dump(mode="json"), request, "mission", "planner",
              lambda: PlannerClient(bus, settings.robot, timeout_s=settings.request_timeout_s).submit(
                  MissionRequest(mission_id=job_id, instruction=body.instruction, map_id=body.map_id,
                                 options=body.options)))
    url, events_url = _links(job_id)
    response.headers["Location"] = url
    row = store.get_job(job_id)
    return JobCreated(id=job_id, state=row.state if row else JobState.QUEUED, url=url, events_url=events_url)


@router.get("", response_model=MissionPage)
def list_missions(store: StoreDep,
                  state: Annotated[list[JobState] | None, Query(description="keep these states")] = None,
                  limit: Annotated[int, Query(ge=1, le=500)] = 50,
                  offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0) -> MissionPage:
    """Missions, newest first, paged and filterable by state (``?state=running&state=queued``)."""
    rows, total = store.list_jobs(JobKind.MISSION, states=state, limit=limit, offset=offset)
    return MissionPage(items=[_summary(r) for r in rows], total=total, limit=limit, offset=offset)




@router.get("/{mission_id}", response_model=MissionRecord, responses=RECORD_DOC)
def get_mission(mission_id: MissionId, cache: CacheDep, if_none_match: IfNoneMatch = None) -> Response:
    """State, step, trajectory, decisions, metrics (when the episode has a goal), tokens and cost.

    Served encoded from a per-revision cache with an ``ETag``: poll with ``If-None-Match`` and an
    unchanged record costs a bodiless 304."""
    entry = cache.get(mission_id, JobKind.MISSION, mission_record)
    if entry is None:
        raise GatewayError(f"no mission {mission_id!r}", 404)
    return record_response(entry, if_none_match)


@router.post("/{mission_id}/cancel", response_model=JobCreated, status_code=status.HTTP_202_ACCEPTED,
             dependencies=[Authorized], responses={401: {}, 404: {}, 409: {}, 503: {}})
def cancel(mission_id: MissionId, request: Request, bus: BusDep, store: StoreDep, settings: SettingsDep) -> JobCreated:
    """Ask the planner to stop the mission; its ``cancelled`` event follows on the stream. A mission no
    live planner runs (an orphan: its planner died or restarted) is cancelled here at once."""
    # Every planner is asked: with replicas, the one zenoh would pick need not be the one running it.
    row = cancel_job(store, JobKind.MISSION, mission_id, request, "planner", lambda: PlannerClient(
        bus, settings.robot, timeout_s=settings.request_timeout_s).cancel_everywhere(mission_id))
    url, events_url = _links(mission_id)
    return JobCreated(id=mission_id, state=row.state, url=url, events_url=events_url)




@router.get("/{mission_id}/events", response_class=StreamingResponse, responses=SSE_DOC)
def mission_events(mission_id: MissionId, store: StoreDep, hub: HubDep, settings: SettingsDep,
                   last_event_id: LastEventId = None, after: After = None):
    """Server-Sent Events: the stored events after ``Last-Event-ID`` (or ``?after=``), then live ones."""
    return events_response(JobKind.MISSION, mission_id, store, hub, settings, last_event_id, after)


@router.get("/{mission_id}/history", response_model=list[EventRecord], responses={404: {}})
def mission_history(mission_id: MissionId, store: StoreDep,
                    after: Annotated[int, Query(ge=-1, le=2**31 - 1)] = -1,
                    limit: Annotated[int, Query(ge=1, le=1000)] = 200) -> list[EventRecord]:
    """The stored events as JSON (for clients that do not speak SSE), images by URL."""
    _get(store, mission_id)
    return [EventRecord(**event_json(JobKind.MISSION, e)) for e in store.events(mission_id, after, limit)]


@router.get("/{mission_id}/events/{seq}/images/{name}.jpg", response_class=Response, responses=IMAGE_DOC)
def mission_image(mission_id: MissionId, seq: Seq, name: ImageName, store: StoreDep) -> Response:
    """One JPEG of one event (panorama, map, cand_<i>_observed, cand_<i>_anticipated, ...)."""
    return image_response(store, mission_id, seq, name)
