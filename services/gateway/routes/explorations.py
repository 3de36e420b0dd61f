"""Explorations: pre-explore the robot's current scene and reconstruct it into a map; cancel one."""

from __future__ import annotations

import uuid
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.gateway.cache import record_response
from services.gateway.deps import Authorized, BusDep, CacheDep, HubDep, SettingsDep, StoreDep
from services.gateway.errors import GatewayError
from services.gateway.records import ExplorationPage, ExplorationRecord, JobCreated, JobKind
from services.gateway.jobs import cancel_job, events_response, image_response, start_job
from services.gateway.params import (
    IMAGE_DOC, RECORD_DOC, SEGMENT, SSE_DOC, After, ExplorationId, IfNoneMatch, ImageName, LastEventId, Seq,
)
from services.gateway.store import JobRow
from shared.clients import MapperClient
from shared.schemas import ExplorationRequest, JobState, check_free_form

router = APIRouter(prefix="/explorations", tags=["explorations"])


class ExplorationCreate(BaseModel):
    """``POST /explorations``: explore the current scene and store the reconstruction as ``map_id``."""

    model_config = ConfigDict(extra="forbid")

    map_id: str | None = Field(None, pattern=SEGMENT, description="name of the map to build (default: generated)")
    max_steps: int | None = Field(None, ge=1, le=100_000)  # None: the mapper's area-scaled budget
    reconstruction: str = Field("rgbd", pattern=SEGMENT, description="regional reconstruction backend")
    options: dict[str, Any] = Field(default_factory=dict)
    record: bool | None = Field(None, description="write a Rerun recording (.rrd); None: the gateway's setting")

    @field_validator("options")
    @classmethod
    def _options(cls, v: dict[str, Any]) -> dict[str, Any]:
        return check_free_form(v, "options")  # the bus message refuses the same: a 422 here, not a 500


def exploration_record(row: JobRow) -> ExplorationRecord:
    s = row.summary
    return ExplorationRecord(
        id=row.id, kind=JobKind.EXPLORATION, state=row.state, step=row.step, last_seq=row.last_seq,
        created_s=row.created_s, updated_s=row.updated_s, started_s=s.get("started_s"),
        finished_s=s.get("finished_s"), error=s.get("error"), message=s.get("message"),
        images=s.get("images", {}), url=f"/explorations/{row.id}", events_url=f"/explorations/{row.id}/events",
        map_id=s.get("map_id") or row.request.get("map_id"), progress=s.get("progress"), stage=s.get("stage"),
        request=row.request, prompt_tokens=s.get("prompt_tokens", 0), completion_tokens=s.get("completion_tokens", 0),
        cost_usd=s.get("cost_usd", 0.0))


def _get(store, job_id: str) -> JobRow:
    row = store.get_job(job_id, JobKind.EXPLORATION)
    if row is None:
        raise GatewayError(f"no exploration {job_id!r}", 404)
    return row


@router.post("", response_model=JobCreated, status_code=status.HTTP_202_ACCEPTED, dependencies=[Authorized],
             responses={401: {}, 409: {}, 422: {}, 503: {}})
def submit(body: ExplorationCreate, http_request: Request, bus: BusDep, store: StoreDep, settings: SettingsDep,
           response: Response) -> JobCreated:
    """Start pre-exploration, tour recording and reconstruction of the robot's current scene."""
    job_id = f"x-{uuid.uuid4().hex[:16]}"
    map_id = body.map_id or f"map-{job_id[2:10]}"
    start_job(store, JobKind.EXPLORATION, job_id, {**body.model_dump(mode="json"), "map_id": map_id}, http_request,
              "exploration", "mapper",
              lambda: MapperClient(bus, settings.robot, timeout_s=settings.request_timeout_s).explore(
                  ExplorationRequest(exploration_id=job_id, map_id=map_id, max_steps=body.max_steps,
                                     reconstruction=body.reconstruction, options=body.options, record=body.record)))
    response.headers["Location"] = f"/explorations/{job_id}"
    return JobCreated(id=job_id, state=JobState.QUEUED, url=f"/explorations/{job_id}",
                      events_url=f"/explorations/{job_id}/events")


@router.get("", response_model=ExplorationPage)
def list_explorations(store: StoreDep,
                      state: Annotated[list[JobState] | None, Query()] = None,
                      limit: Annotated[int, Query(ge=1, le=500)] = 50,
                      offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0) -> ExplorationPage:
    """Explorations, newest first."""
    rows, total = store.list_jobs(JobKind.EXPLORATION, states=state, limit=limit, offset=offset)
    return ExplorationPage(items=[exploration_record(r) for r in rows], total=total, limit=limit, offset=offset)


@router.get("/{exploration_id}", response_model=ExplorationRecord, responses=RECORD_DOC)
def get_exploration(exploration_id: ExplorationId, cache: CacheDep, if_none_match: IfNoneMatch = None) -> Response:
    """State, stage and progress (0-1); ``map_id`` names the map it builds. ETag / 304 as for missions."""
    entry = cache.get(exploration_id, JobKind.EXPLORATION, exploration_record)
    if entry is None:
        raise GatewayError(f"no exploration {exploration_id!r}", 404)
    return record_response(entry, if_none_match)


@router.post("/{exploration_id}/cancel", response_model=JobCreated, status_code=status.HTTP_202_ACCEPTED,
             dependencies=[Authorized], responses={401: {}, 404: {}, 409: {}, 503: {}})
def cancel(exploration_id: ExplorationId, request: Request, bus: BusDep, store: StoreDep,
           settings: SettingsDep) -> JobCreated:
    """Ask the mapper to stop the exploration: it stops within one exploration step or tour move, or
    cancels the map build it waits on (which then stores nothing). Its ``cancelled`` event, naming the
    stage it stopped in, follows on the stream; an exploration whose build had already stored the map
    ends succeeded. One no live mapper runs (an orphan) is cancelled here at once."""
    row = cancel_job(store, JobKind.EXPLORATION, exploration_id, request, "mapper", lambda: MapperClient(
        bus, settings.robot, timeout_s=settings.request_timeout_s).cancel_everywhere(exploration_id))
    return JobCreated(id=exploration_id, state=row.state, url=f"/explorations/{exploration_id}",
                      events_url=f"/explorations/{exploration_id}/events")


@router.get("/{exploration_id}/events", response_class=StreamingResponse, responses=SSE_DOC)
def exploration_events(exploration_id: ExplorationId, store: StoreDep, hub: HubDep, settings: SettingsDep,
                       last_event_id: LastEventId = None, after: After = None):
    """Server-Sent Events of the exploration, resumable with ``Last-Event-ID``."""
    return events_response(JobKind.EXPLORATION, exploration_id, store, hub, settings, last_event_id, after)


@router.get("/{exploration_id}/events/{seq}/images/{name}.jpg", response_class=Response, responses=IMAGE_DOC)
def exploration_image(exploration_id: ExplorationId, seq: Seq, name: ImageName, store: StoreDep) -> Response:
    return image_response(store, exploration_id, seq, name)
