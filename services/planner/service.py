"""planner service: runs navigation missions (the loop of Section 4.3) over the bus.

``MISSION_SUBMIT`` queues a mission job (:mod:`shared.jobs`; one runs at a time: a robot has one body);
``MISSION_CANCEL`` cancels a queued or running one. The job is the core's
:func:`~services.planner.core.mission.run_mission`, wired here to bus clients. Each mission publishes its events on
``MISSION_EVENTS`` with a gap-free sequence: started, one per step (pose, candidates, decision,
reasoning, timings, JPEG views), then finished (metrics when the mission has a goal) or error.
"""

from __future__ import annotations

import logging
from typing import Any

from pydantic import Field

from services.planner.core import POLICIES
from services.planner.core.mission import run_mission
from shared import keys
from shared.clients import MapClient, MapperClient, RendererClient, RobotClient
from shared.events import jpeg
from shared.jobs import JobContext, JobEnd, JobRunner
from shared.runner import Node, Service, ServiceSettings
from shared.schemas import CancelRequest, JobAccepted, MissionRequest

log = logging.getLogger(__name__)


class PlannerSettings(ServiceSettings):
    default_policy_config: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="per policy backend, the config used when a mission gives none")
    max_queued: int = Field(16, ge=1, le=1000)
    call_timeout_s: float = Field(60.0, gt=0, description="timeout of one call to another service")


class PlannerService(Service[PlannerSettings]):
    name = "planner"
    Settings = PlannerSettings

    def __init__(self, settings: PlannerSettings):
        super().__init__(settings)
        self._jobs: JobRunner | None = None
        self._node: Node | None = None

    def backends(self) -> dict[str, str]:
        return {"policies": ",".join(POLICIES.names())}

    def start(self, node: Node) -> None:
        self._node = node
        # One worker: a robot has one body, so its missions queue behind each other.
        self._jobs = JobRunner(node.bus, name="mission", workers=1, max_queued=self.settings.max_queued)
        node.serve(keys.MISSION_SUBMIT.format(robot=node.robot), MissionRequest, self.submit, workers=1)
        node.serve(keys.MISSION_CANCEL.format(robot=node.robot), CancelRequest, self.cancel, workers=1)

    def stop(self) -> None:
        if self._jobs is not None:
            self._jobs.close()

    # --- queryables ------------------------------------------------------------------------------------
    def submit(self, req: MissionRequest) -> JobAccepted:
        node, jobs = self._node, self._jobs
        assert node is not None and jobs is not None
        keys.validate_segment(req.mission_id, "mission id")
        keys.validate_segment(req.map_id, "map id")
        if req.options.policy not in POLICIES.names():
            raise ValueError(f"unknown policy {req.options.policy!r}; known: {', '.join(POLICIES.names())}")
        return jobs.submit(req.mission_id, lambda ctx: self._mission(ctx, req),
                           keys.MISSION_EVENTS.format(robot=node.robot, mission=req.mission_id))

    def cancel(self, req: CancelRequest) -> JobAccepted:
        assert self._jobs is not None
        return self._jobs.cancel(req.mission_id)

    # --- the job: bus clients wired into the core's mission ------------------------------------------------
    def _mission(self, ctx: JobContext, req: MissionRequest) -> JobEnd:
        node = self._node
        assert node is not None
        s = self.settings
        opts = req.options
        policy = POLICIES.create(opts.policy, opts.policy_config or s.default_policy_config.get(opts.policy) or None)
        try:
            return run_mission(
                ctx, req, robot=RobotClient(node.bus, node.robot, timeout_s=s.call_timeout_s),
                predictor=MapperClient(node.bus, node.robot, timeout_s=s.call_timeout_s),
                renderer=RendererClient(node.bus, timeout_s=s.call_timeout_s),
                maps=MapClient(node.bus, timeout_s=s.call_timeout_s), policy=policy, jpeg=jpeg)
        finally:
            policy.close()
