"""mapper service: waypoint prediction on request, and pre-exploration jobs.

``MAPPER_PREDICT`` answers candidates for a panorama (the planner calls it at every step).
``MAPPER_EXPLORE`` accepts an exploration job (:mod:`shared.jobs`); the job itself is the core's
:func:`~services.mapper.core.exploration_job.explore`, wired here to robot-io and the reconstructor
over the bus. Its progress is published as events of the exploration.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from pydantic import Field

from services.mapper.core import DEFAULT_PREDICTOR, PREDICTORS, WaypointPredictor
from services.mapper.core.exploration_job import explore
from shared import keys
from shared.clients import MapClient, RobotClient
from shared.jobs import JobRunner
from shared.runner import Node, Service, ServiceSettings
from shared.schemas import CameraIntrinsics, CandidateSet, ExplorationRequest, JobAccepted, Panorama

log = logging.getLogger(__name__)


class MapperSettings(ServiceSettings):
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
        self._jobs: JobRunner | None = None
        self._node: Node | None = None

    def backends(self) -> dict[str, str]:
        return {"predictor": self.settings.predictor}

    def start(self, node: Node) -> None:
        self._node = node
        self._jobs = JobRunner(node.bus, name="exploration", workers=1, max_queued=1)
        node.serve(keys.MAPPER_PREDICT.format(robot=node.robot), Panorama, self.predict)
        node.serve(keys.MAPPER_EXPLORE.format(robot=node.robot), ExplorationRequest, self.submit, workers=1)

    def stop(self) -> None:
        if self._jobs is not None:
            self._jobs.close()

    def predict(self, pano: Panorama) -> CandidateSet:
        return CandidateSet(pose=pano.pose, candidates=self.predictor.predict(pano))

    def submit(self, req: ExplorationRequest) -> JobAccepted:
        node, jobs = self._node, self._jobs
        assert node is not None and jobs is not None
        keys.validate_segment(req.exploration_id, "exploration id")
        keys.validate_segment(req.map_id, "map id")
        s = self.settings
        # A robot has one body: a second exploration is refused, not queued behind the first.
        with self._lock:
            if jobs.busy():
                return JobAccepted(job_id=req.exploration_id, accepted=False,
                                   reason="an exploration is already running on this robot")
            robot = RobotClient(node.bus, node.robot, recording_px=s.tour_frame_px,
                                recording_prefix=req.exploration_id,
                                observe_camera=CameraIntrinsics(width_px=s.explore_camera_px,
                                                                height_px=s.explore_camera_px))
            maps = MapClient(node.bus, build_stall_s=s.build_stall_s)
            return jobs.submit(req.exploration_id, lambda ctx: explore(
                ctx, req, robot=robot, maps=maps, tour_rate_hz=s.tour_rate_hz,
                publish_graph=lambda g: node.bus.publish(keys.MAPPER_GRAPH.format(robot=node.robot), g),
                publish_tour=lambda t: node.bus.publish(
                    keys.MAPPER_TOURS.format(robot=node.robot, region=str(t.region)), t)),
                keys.EXPLORATION_EVENTS.format(robot=node.robot, exploration=req.exploration_id))

