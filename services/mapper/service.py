"""mapper service: waypoint prediction on request, and pre-exploration jobs.

``MAPPER_PREDICT`` answers candidates for a panorama (the planner calls it at every step).
``MAPPER_EXPLORE`` accepts an exploration job (:mod:`shared.jobs`); the job itself is the core's
:func:`~services.mapper.core.exploration_job.explore`, wired here to robot-io and the reconstructor
over the bus. Its progress is published as events of the exploration. ``EXPLORATION_CANCEL`` cancels
the robot's exploration: it stops within one exploration step or tour move, or cancels the map build
it waits on, and ends ``cancelled`` with the stage it was in.

One mapper serves any number of robots: its queryables are served on a wildcard in the robot segment
(or on the concrete keys of ``serve_robots``, so that replicas split the robots), and the robot id is
taken from the key each request came on, never from its payload. Prediction is stateless per request;
explorations are one at a time per robot (one body), concurrent across robots.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from pydantic import Field

from services.mapper.core import DEFAULT_PREDICTOR, PREDICTORS, WaypointPredictor
from shared import keys
from shared.clients import MapClient, RobotClient
from shared.jobs import JobRunner
from shared.runner import FleetServiceSettings, Node, Service
from shared.schemas import (
    CameraIntrinsics, CandidateSet, ExplorationCancelRequest, ExplorationRequest, JobAccepted, Panorama,
)

log = logging.getLogger(__name__)


class MapperSettings(FleetServiceSettings):
    predictor: str = Field(DEFAULT_PREDICTOR, description="waypoint predictor backend")
    predictor_config: dict[str, Any] = Field(default_factory=dict)
    explore_camera_px: int = Field(96, ge=32, le=1024,
                                   description="panorama size while exploring (depth only needs little)")
    tour_rate_hz: float = Field(4.0, gt=0, le=30)
    tour_frame_px: int = Field(128, ge=32, le=1024)
    build_stall_s: float = Field(300.0, gt=0, le=3600,
                                 description="a map build that sends no event for this long has failed")


class MapperService(Service[MapperSettings]):
    name = "mapper"
    Settings = MapperSettings

    def __init__(self, settings: MapperSettings):
        super().__init__(settings)
        self.predictor: WaypointPredictor = PREDICTORS.create(settings.predictor, settings.predictor_config or None)
        self._lock = threading.Lock()
        self._jobs: dict[str, JobRunner] = {}  # robot id -> its exploration runner
        self._closed = False
        self._node: Node | None = None

    def backends(self) -> dict[str, str]:
        return {"predictor": self.settings.predictor}

    def start(self, node: Node) -> None:
        self._node = node
        routes = self.settings.serve_robots
        for key in keys.robot_routes(keys.MAPPER_PREDICT, routes):
            node.serve(key, Panorama, self.predict)
        for key in keys.robot_routes(keys.MAPPER_EXPLORE, routes):
            node.serve(key, ExplorationRequest, self.submit, workers=1, keyed=True)
        for key in keys.robot_routes(keys.EXPLORATION_CANCEL, routes):
            node.serve(key, ExplorationCancelRequest, self.cancel, workers=1, keyed=True)

    def stop(self) -> None:
        with self._lock:
            self._closed = True
            runners = list(self._jobs.values())
        for jobs in runners:
            jobs.close()

    def predict(self, pano: Panorama) -> CandidateSet:
        return CandidateSet(pose=pano.pose, candidates=self.predictor.predict(pano))

    def submit(self, key: str, req: ExplorationRequest) -> JobAccepted:
        # Here, not at module level: exploration (scipy, networkx, the explorer, regions and tours) costs ~0.6 s
        # of CPU to import, and most mapper processes only ever predict waypoints.
        from services.mapper.core.exploration_job import explore, request_discovery_config

        node = self._node
        assert node is not None
        robot_id = keys.robot_of(keys.MAPPER_EXPLORE, key)
        try:  # refused before it is accepted: a bad profile or knob never becomes a failed job
            request_discovery_config(req)
        except (KeyError, ValueError) as exc:  # pydantic's ValidationError is a ValueError
            return JobAccepted(job_id=req.exploration_id, accepted=False, reason=f"bad exploration options: {exc}")
        s = self.settings
        with self._lock:
            jobs = self._jobs.get(robot_id)
            if jobs is None:
                if self._closed or len(self._jobs) >= s.max_robots:
                    return JobAccepted(job_id=req.exploration_id, accepted=False,
                                       reason=f"this mapper already serves {s.max_robots} robots")
                jobs = self._jobs[robot_id] = JobRunner(node.bus, name=f"exploration of {robot_id}", workers=1,
                                                        max_queued=1)
            # A robot has one body: a second exploration is refused, not queued behind the first.
            if jobs.busy():
                return JobAccepted(job_id=req.exploration_id, accepted=False,
                                   reason="an exploration is already running on this robot")
            robot = RobotClient(node.bus, robot_id, recording_px=s.tour_frame_px,
                                recording_prefix=req.exploration_id,
                                observe_camera=CameraIntrinsics(width_px=s.explore_camera_px,
                                                                height_px=s.explore_camera_px))
            maps = MapClient(node.bus, build_stall_s=s.build_stall_s)
            return jobs.submit(req.exploration_id, lambda ctx: explore(
                ctx, req, robot=robot, maps=maps, tour_rate_hz=s.tour_rate_hz,
                publish_graph=lambda g: node.bus.publish(keys.MAPPER_GRAPH.format(robot=robot_id), g),
                publish_tour=lambda t: node.bus.publish(
                    keys.MAPPER_TOURS.format(robot=robot_id, region=str(t.region)), t)),
                keys.EXPLORATION_EVENTS.format(robot=robot_id, exploration=req.exploration_id))

    def cancel(self, key: str, req: ExplorationCancelRequest) -> JobAccepted:
        """Cancel the key's robot's exploration ``req.exploration_id`` (refused when it runs none such)."""
        robot_id = keys.robot_of(keys.EXPLORATION_CANCEL, key)
        with self._lock:
            jobs = self._jobs.get(robot_id)
        if jobs is None:
            return JobAccepted(job_id=req.exploration_id, accepted=False, reason="no such exploration here")
        return jobs.cancel(req.exploration_id)

    def active(self) -> dict[str, list[str]]:
        """Queued and running exploration ids per robot."""
        with self._lock:
            runners = dict(self._jobs)
        return {robot: jobs.active() for robot, jobs in runners.items()}
