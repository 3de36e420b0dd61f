"""planner service: runs navigation missions (the loop of Section 4.3) over the bus.

One planner serves any number of robots: it serves ``MISSION_SUBMIT`` / ``MISSION_CANCEL`` on a wildcard
in the robot segment (``ant/*/planner/missions/submit``), or on the concrete keys of ``serve_robots``
only (replicas split the robots between them), and takes the robot id from the key each request came
on - never from its payload - so a request on robotX's key can only start or cancel robotX's missions.
Each robot has its own mission queue (:mod:`shared.jobs`; one mission runs at a time per robot: a robot
has one body), so missions of different robots run concurrently. The job is the core's
:func:`~services.planner.core.mission.run_mission`, wired here to bus clients. Each mission publishes its events on
``MISSION_EVENTS`` with a gap-free sequence: started, one per step (pose, candidates, decision,
reasoning, timings, JPEG views), then finished (metrics when the mission has a goal) or error.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from pydantic import Field

from services.planner.core import POLICIES
from services.planner.core.mission import run_mission
from shared import keys
from shared.clients import MapClient, MapperClient, RendererClient, RobotClient
from shared.events import jpeg
from shared.jobs import JobContext, JobEnd, JobRunner
from shared.runner import FleetServiceSettings, Node, Service
from shared.schemas import CancelRequest, JobAccepted, MissionRequest

log = logging.getLogger(__name__)


class PlannerSettings(FleetServiceSettings):
    default_policy_config: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="per policy backend, the config used when a mission gives none")
    max_queued: int = Field(16, ge=1, le=1000, description="missions queued per robot")
    call_timeout_s: float = Field(60.0, gt=0, description="timeout of one call to another service")


class PlannerService(Service[PlannerSettings]):
    name = "planner"
    Settings = PlannerSettings

    def __init__(self, settings: PlannerSettings):
        super().__init__(settings)
        self._jobs: dict[str, JobRunner] = {}  # robot id -> its mission queue
        self._jobs_lock = threading.Lock()
        self._closed = False
        self._node: Node | None = None

    def backends(self) -> dict[str, str]:
        return {"policies": ",".join(POLICIES.names())}

    def start(self, node: Node) -> None:
        self._node = node
        routes = self.settings.serve_robots
        for key in keys.robot_routes(keys.MISSION_SUBMIT, routes):
            node.serve(key, MissionRequest, self.submit, workers=1, keyed=True)
        for key in keys.robot_routes(keys.MISSION_CANCEL, routes):
            node.serve(key, CancelRequest, self.cancel, workers=1, keyed=True)

    def stop(self) -> None:
        with self._jobs_lock:
            self._closed = True
            runners = list(self._jobs.values())
        for jobs in runners:
            jobs.close()

    def _runner(self, robot: str) -> JobRunner | None:
        """The robot's mission queue, made at its first mission (None: too many robots already)."""
        node = self._node
        assert node is not None
        with self._jobs_lock:
            jobs = self._jobs.get(robot)
            if jobs is None and not self._closed and len(self._jobs) < self.settings.max_robots:
                # One worker: a robot has one body, so its missions queue behind each other.
                jobs = self._jobs[robot] = JobRunner(node.bus, name=f"mission of {robot}", workers=1,
                                                     max_queued=self.settings.max_queued)
            return jobs

    # --- queryables ------------------------------------------------------------------------------------
    def submit(self, key: str, req: MissionRequest) -> JobAccepted:
        robot = keys.robot_of(keys.MISSION_SUBMIT, key)
        if req.options.policy not in POLICIES.names():
            raise ValueError(f"unknown policy {req.options.policy!r}; known: {', '.join(POLICIES.names())}")
        jobs = self._runner(robot)
        if jobs is None:
            return JobAccepted(job_id=req.mission_id, accepted=False,
                               reason=f"this planner already serves {self.settings.max_robots} robots")
        return jobs.submit(req.mission_id, lambda ctx: self._mission(ctx, robot, req),
                           keys.MISSION_EVENTS.format(robot=robot, mission=req.mission_id))

    def cancel(self, key: str, req: CancelRequest) -> JobAccepted:
        robot = keys.robot_of(keys.MISSION_CANCEL, key)
        with self._jobs_lock:
            jobs = self._jobs.get(robot)
        if jobs is None:
            return JobAccepted(job_id=req.mission_id, accepted=False, reason="no such mission here")
        return jobs.cancel(req.mission_id)

    def active(self) -> dict[str, list[str]]:
        """Queued and running mission ids per robot."""
        with self._jobs_lock:
            runners = dict(self._jobs)
        return {robot: jobs.active() for robot, jobs in runners.items()}

    # --- the job: bus clients wired into the core's mission ------------------------------------------------
    def _mission(self, ctx: JobContext, robot: str, req: MissionRequest) -> JobEnd:
        node = self._node
        assert node is not None
        s = self.settings
        opts = req.options
        policy = POLICIES.create(opts.policy, opts.policy_config or s.default_policy_config.get(opts.policy) or None)
        try:
            return run_mission(
                ctx, req, robot=RobotClient(node.bus, robot, timeout_s=s.call_timeout_s),
                predictor=MapperClient(node.bus, robot, timeout_s=s.call_timeout_s),
                renderer=RendererClient(node.bus, timeout_s=s.call_timeout_s),
                maps=MapClient(node.bus, timeout_s=s.call_timeout_s), policy=policy, jpeg=jpeg)
        finally:
            policy.close()
