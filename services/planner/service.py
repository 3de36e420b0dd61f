"""planner service: runs navigation missions (the loop of Section 4.3) over the bus.

``MISSION_SUBMIT`` queues a mission (one runs at a time: a robot has one body);
``MISSION_CANCEL`` cancels a queued or running one. Each mission publishes its events on
``MISSION_EVENTS`` with a gap-free sequence: started, one per step (pose, candidates, decision,
reasoning, timings, JPEG views), then finished (metrics when the mission has a goal) or error.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any

from pydantic import Field

from services.planner.core import POLICIES
from services.planner.core.mission import MissionCancelled, MissionLoop
from shared import keys
from shared.bus.typed import RemoteError
from shared.clients import MapClient, MapperClient, RendererClient, RobotClient
from shared.events import EventStream, jpeg
from shared.runner import Node, Service, ServiceSettings
from shared.schemas import (
    CancelRequest, JobCancelled, JobFailed, MissionAccepted, MissionEventKind, MissionFinished, MissionRequest,
    MissionState, UsageData,
)

log = logging.getLogger(__name__)


class PlannerSettings(ServiceSettings):
    default_policy_config: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="per policy backend, the config used when a mission gives none")
    max_queued: int = Field(16, ge=1, le=1000)
    call_timeout_s: float = Field(60.0, gt=0, description="timeout of one call to another service")


class PlannerService(Service):
    name = "planner"
    Settings = PlannerSettings

    def __init__(self, settings: PlannerSettings):
        super().__init__(settings)
        self._queue: queue.Queue[MissionRequest | None] = queue.Queue(maxsize=settings.max_queued)
        self._cancel: dict[str, threading.Event] = {}
        self._lock = threading.Lock()
        self._worker: threading.Thread | None = None
        self._node: Node | None = None

    def backends(self) -> dict[str, str]:
        return {"policies": ",".join(POLICIES.names())}

    def start(self, node: Node) -> None:
        self._node = node
        node.serve(keys.MISSION_SUBMIT.format(robot=node.robot), MissionRequest, self.submit, workers=1)
        node.serve(keys.MISSION_CANCEL.format(robot=node.robot), CancelRequest, self.cancel, workers=1)
        self._worker = threading.Thread(target=self._work, name="missions", daemon=True)
        self._worker.start()

    def stop(self) -> None:
        for ev in list(self._cancel.values()):
            ev.set()
        try:
            self._queue.put_nowait(None)
        except queue.Full:
            pass
        if self._worker:
            self._worker.join(5.0)

    # --- queryables ------------------------------------------------------------------------------------
    def submit(self, req: MissionRequest) -> MissionAccepted:
        keys.validate_segment(req.mission_id, "mission id")
        keys.validate_segment(req.map_id, "map id")
        if req.options.policy not in POLICIES.names():
            raise ValueError(f"unknown policy {req.options.policy!r}; known: {', '.join(POLICIES.names())}")
        with self._lock:
            if req.mission_id in self._cancel:
                return MissionAccepted(mission_id=req.mission_id, accepted=False, reason="mission id already used")
            try:
                self._queue.put_nowait(req)
            except queue.Full:
                return MissionAccepted(mission_id=req.mission_id, accepted=False,
                                       reason=f"{self.settings.max_queued} missions already queued")
            self._cancel[req.mission_id] = threading.Event()
        return MissionAccepted(mission_id=req.mission_id, accepted=True)

    def cancel(self, req: CancelRequest) -> MissionAccepted:
        ev = self._cancel.get(req.mission_id)
        if ev is None:
            return MissionAccepted(mission_id=req.mission_id, accepted=False, reason="no such mission here")
        ev.set()
        return MissionAccepted(mission_id=req.mission_id, accepted=True)

    # --- the worker ----------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            req = self._queue.get()
            if req is None:
                return
            try:
                self._run(req)
            finally:
                with self._lock:
                    self._cancel.pop(req.mission_id, None)

    def _run(self, req: MissionRequest) -> None:
        node = self._node
        assert node is not None
        s: PlannerSettings = self.settings  # type: ignore[assignment]
        events = EventStream(node.bus, keys.MISSION_EVENTS.format(robot=node.robot, mission=req.mission_id),
                             req.mission_id)
        cancel = self._cancel[req.mission_id]
        opts = req.options
        policy = None
        try:
            if cancel.is_set():
                raise MissionCancelled()
            cfg = opts.policy_config or s.default_policy_config.get(opts.policy) or None
            policy = POLICIES.create(opts.policy, cfg)
            info = MapClient(node.bus, timeout_s=s.call_timeout_s).info(req.map_id)
            loop = MissionLoop(
                robot=RobotClient(node.bus, node.robot, timeout_s=s.call_timeout_s),
                predictor=MapperClient(node.bus, node.robot, timeout_s=s.call_timeout_s),
                renderer=RendererClient(node.bus, timeout_s=s.call_timeout_s),
                policy=policy,
                emit=lambda kind, state, **kw: events.emit(kind, state, **kw),
                cancel=cancel, label_names=info.label_names, jpeg=jpeg,
            )
            out = loop.run(req.mission_id, req.instruction, req.map_id, opts)
            # A failed mission carries its cause as the error; a stop with a caveat as a reason.
            failed = out.state == MissionState.FAILED
            data = MissionFinished(
                stop_called=out.stop_called, steps=out.steps, trajectory_m=[tuple(p) for p in out.trajectory_m.tolist()],
                metrics=out.metrics, usage=UsageData(**policy.usage.to_dict()),
                step_latency_s=[round(x, 4) for x in out.step_latency_s],
                reason="" if failed else out.reason, error=out.reason if failed else "")
            events.emit(MissionEventKind.FINISHED, out.state, step=out.steps, data=data)
        except MissionCancelled:
            events.emit(MissionEventKind.FINISHED, MissionState.CANCELLED, data=JobCancelled())
        except RemoteError as exc:
            log.warning("mission %s failed: %s", req.mission_id, exc)
            events.emit(MissionEventKind.ERROR, MissionState.FAILED,
                        data=JobFailed(error=f"a service did not answer properly: {exc}"))
        except Exception as exc:
            log.exception("mission %s failed", req.mission_id)
            events.emit(MissionEventKind.ERROR, MissionState.FAILED, data=JobFailed(error=f"{type(exc).__name__}: {exc}"))
        finally:
            if policy is not None:
                policy.close()
