"""The robot's scene: what it is (``GET /robot/scene``) and switching it (``POST /robot/scene``).

Switching is for simulator backends (evaluation over many houses): robot-io loads the new scene and
answers its summary, or refuses a spec it cannot read (422). A switch under a running mission or
exploration would pull the floor from under it, so it is refused (409) while one is queued or
running on this robot, and no mission or exploration may start while a switch is under way.
"""

from __future__ import annotations

import logging
from typing import Annotated

from fastapi import APIRouter, Request
from pydantic import BaseModel, ConfigDict, StringConstraints

from services.gateway.deps import Authorized, BusDep, SettingsDep, StoreDep
from services.gateway.errors import GatewayError, ask
from services.gateway.jobs import open_jobs, scene_lock
from shared.clients import RobotClient
from shared.schemas import SceneSummary

log = logging.getLogger(__name__)
router = APIRouter(prefix="/robot", tags=["robot"])

class SceneLoad(BaseModel):
    """``POST /robot/scene``: ``generated:<seed>[:floors=2]`` or a mesh path robot-io can read."""

    model_config = ConfigDict(extra="forbid")

    # No control characters: the spec ends up in logs and file paths.
    scene: Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=1000,
                                            pattern=r"^[^\x00-\x1f\x7f]+$")]


@router.get("/scene", response_model=SceneSummary, responses={503: {}, 504: {}})
def get_scene(bus: BusDep, settings: SettingsDep) -> SceneSummary:
    """The scene robot-io is in: name, bounds, floors, reachable area, rooms, start pose."""
    return ask("robot-io cannot tell its scene",
               lambda: RobotClient(bus, settings.robot, timeout_s=settings.request_timeout_s).scene())


@router.post("/scene", response_model=SceneSummary, dependencies=[Authorized],
             responses={401: {}, 409: {"description": "a mission or exploration is running, or another switch"},
                        422: {"description": "a spec robot-io cannot load"}, 503: {}, 504: {}})
def load_scene(body: SceneLoad, request: Request, bus: BusDep, store: StoreDep, settings: SettingsDep) -> SceneSummary:
    """Switch the robot (simulator) to another scene and return its summary.

    Blocks until robot-io has loaded it (up to ``scene_timeout_s``); 409 while a mission or
    exploration is queued or running on the robot, or while another switch is under way."""
    lock = scene_lock(request)
    if not lock.acquire(blocking=False):
        raise GatewayError("another scene switch is under way", 409)
    try:
        busy = open_jobs(store)
        if busy:
            raise GatewayError("cannot switch scenes while jobs run on the robot: " + ", ".join(busy), 409)
        summary = ask(f"robot-io cannot load {body.scene!r}", lambda: RobotClient(bus, settings.robot).load_scene(
            body.scene, timeout_s=settings.scene_timeout_s))
    finally:
        lock.release()
    log.info("robot %s switched to scene %s", settings.robot, summary.scene)
    return summary
