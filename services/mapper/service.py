"""mapper service: waypoint prediction on request, and pre-exploration jobs.

``MAPPER_PREDICT`` answers candidates for a panorama (the planner calls it at every step).
``MAPPER_EXPLORE`` starts Algorithm 1 in a worker thread: it drives robot-io over the bus, records
one tour per region (robot-io publishes the frames, the reconstructor collects them), then asks the
reconstructor to build and store the map. Progress is published as events of the exploration.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from pydantic import Field

from services.mapper.core import (
    DEFAULT_PREDICTOR, PREDICTORS, DiscoveryConfig, RegionRecording, WaypointPredictor, discover, execute_tours,
)
from shared import keys
from shared.bus.typed import RemoteError
from shared.clients import MapClient, RobotClient
from shared.events import EventStream
from shared.runner import Node, Service, ServiceSettings
from shared.schemas import (
    BuildMapRequest, CameraIntrinsics, CandidateSet, ExplorationFinished, ExplorationProgress, ExplorationRequest,
    ExplorationStarted, JobFailed, MissionAccepted, MissionEventKind, MissionState, Panorama, TourRecording,
)

log = logging.getLogger(__name__)


class MapperSettings(ServiceSettings):
    predictor: str = Field(DEFAULT_PREDICTOR, description="waypoint predictor backend")
    predictor_config: dict[str, Any] = Field(default_factory=dict)
    explore_camera_px: int = Field(96, ge=32, le=1024,
                                   description="panorama size while exploring (depth only needs little)")
    tour_rate_hz: float = Field(4.0, gt=0, le=30)
    tour_frame_px: int = Field(128, ge=32, le=1024)


class MapperService(Service):
    name = "mapper"
    Settings = MapperSettings

    def __init__(self, settings: MapperSettings):
        super().__init__(settings)
        self.predictor: WaypointPredictor = PREDICTORS.create(settings.predictor, settings.predictor_config or None)
        self._job_lock = threading.Lock()
        self._job: threading.Thread | None = None
        self._node: Node | None = None

    def backends(self) -> dict[str, str]:
        return {"predictor": self.settings.predictor}

    def start(self, node: Node) -> None:
        self._node = node
        node.serve(keys.MAPPER_PREDICT.format(robot=node.robot), Panorama, self.predict)
        node.serve(keys.MAPPER_EXPLORE.format(robot=node.robot), ExplorationRequest, self.submit, workers=1)

    def predict(self, pano: Panorama) -> CandidateSet:
        return CandidateSet(pose=pano.pose, candidates=self.predictor.predict(pano))

    def submit(self, req: ExplorationRequest) -> MissionAccepted:
        keys.validate_segment(req.exploration_id, "exploration id")
        keys.validate_segment(req.map_id, "map id")
        with self._job_lock:
            if self._job and self._job.is_alive():
                return MissionAccepted(mission_id=req.exploration_id, accepted=False,
                                       reason="an exploration is already running on this robot")
            self._job = threading.Thread(target=self._run, args=(req,), name=f"explore-{req.exploration_id}",
                                         daemon=True)
            self._job.start()
        return MissionAccepted(mission_id=req.exploration_id, accepted=True)

    # --- the exploration job -------------------------------------------------------------------------
    def _run(self, req: ExplorationRequest) -> None:
        node = self._node
        assert node is not None
        events = EventStream(node.bus, keys.EXPLORATION_EVENTS.format(robot=node.robot,
                                                                         exploration=req.exploration_id),
                             req.exploration_id)
        s: MapperSettings = self.settings  # type: ignore[assignment]
        t0 = time.perf_counter()
        try:
            events.emit(MissionEventKind.STARTED, MissionState.RUNNING, data=ExplorationStarted(map_id=req.map_id))
            cam = CameraIntrinsics(width_px=s.explore_camera_px, height_px=s.explore_camera_px)
            robot = RobotClient(node.bus, node.robot, observe_camera=cam)
            cfg = DiscoveryConfig.model_validate(req.options.get("discovery", {}))
            cfg.exploration.max_steps = req.max_steps
            events.emit(MissionEventKind.PROGRESS, MissionState.RUNNING,
                        data=ExplorationProgress(stage="exploring", progress=0.02, message="frontier DFS over waypoints"))
            disc = discover(robot, cfg)
            node.bus.publish(keys.MAPPER_GRAPH.format(robot=node.robot), disc.nav_graph())
            for tour in disc.tour_messages():
                node.bus.publish(keys.MAPPER_TOURS.format(robot=node.robot, region=str(tour.region)), tour)
            nodes = len(disc.result.graph.graph)
            timings_s = {k: round(v, 3) for k, v in disc.timings_s.items()}
            events.emit(MissionEventKind.PROGRESS, MissionState.RUNNING, data=ExplorationProgress(
                stage="touring", progress=0.3, nodes=nodes, regions=len(disc.tours), timings_s=timings_s,
                message=f"explored {nodes} nodes; recording {len(disc.tours)} region tours"))

            recordings: list[TourRecording] = []

            def on_recording(rec: RegionRecording) -> None:
                last = robot.last_recording
                recordings.append(TourRecording(exploration_id=req.exploration_id, recording=last.recording,
                                                region=rec.region, start_pose=rec.start_pose,
                                                frame_count=last.frame_count))
                events.emit(MissionEventKind.PROGRESS, MissionState.RUNNING, data=ExplorationProgress(
                    stage="touring", progress=0.3 + 0.5 * len(recordings) / max(1, len(disc.tours)),
                    region=rec.region, frames=last.frame_count,
                    message=f"region {rec.region}: {last.frame_count} frames ({len(recordings)}/{len(disc.tours)})"))

            class _Recorder:
                # execute_tours opens robot.recording(sink, rate); route it to robot-io's recorder
                # with our frame size, and hand the frames to the bus rather than to a local sink.
                def __getattr__(self, name):
                    return getattr(robot, name)

                def recording(self, sink, rate_hz=s.tour_rate_hz):
                    return robot.recording(sink, rate_hz, max_width_px=s.tour_frame_px,
                                           recording=f"{req.exploration_id}-r{len(recordings)}")

            skipped: list[int] = []

            def on_skip(pt, exc) -> None:
                skipped.append(pt.tour.region)
                events.emit(MissionEventKind.PROGRESS, MissionState.RUNNING, data=ExplorationProgress(
                    stage="touring", progress=0.3 + 0.5 * (len(recordings) + len(skipped)) / max(1, len(disc.tours)),
                    region=pt.tour.region, message=f"region {pt.tour.region} skipped: {exc}"))

            execute_tours(_Recorder(), disc.tours, disc.scene, rate_hz=s.tour_rate_hz, on_recording=on_recording,
                          on_skip=on_skip)
            events.emit(MissionEventKind.PROGRESS, MissionState.RUNNING, data=ExplorationProgress(
                stage="reconstructing", progress=0.85, message=f"reconstructing {len(recordings)} regions"))
            scene = robot.scene()
            info = MapClient(node.bus).build(BuildMapRequest(
                exploration_id=req.exploration_id, map_id=req.map_id, recordings=recordings,
                reconstruction=req.reconstruction, options=req.options.get("reconstruction", {}),
                label_names=scene.label_names, source=f"exploration {req.exploration_id} of {scene.scene}"))
            events.emit(MissionEventKind.FINISHED, MissionState.SUCCEEDED, data=ExplorationFinished(
                map_id=info.map_id, version=info.version, points=info.point_count, regions=len(recordings),
                skipped_regions=skipped, nodes=nodes, timings_s=timings_s,
                wall_s=round(time.perf_counter() - t0, 2)))
        except (RemoteError, Exception) as exc:  # a failed job ends with a reason, never silently
            log.exception("exploration %s failed", req.exploration_id)
            events.emit(MissionEventKind.ERROR, MissionState.FAILED,
                        data=JobFailed(error=f"{type(exc).__name__}: {exc}"))
