"""Scripted robot-io and planner for the runner's tests (like dora's ``MockNode``).

They speak the real contracts (:mod:`shared.keys`, :mod:`shared.schemas`) on any bus: robot-io answers
scene loads (refusing specs that contain ``"broken"``); the planner walks straight towards the goal
in ``step_m`` steps and finishes with VLN-CE metrics computed by :mod:`shared.vln_metrics` (straight-line
geodesics), its usage and step latencies, as the real planner's ``finished`` event carries them.
Instructions containing ``"crash"`` end in an error event; ``"hang"`` never ends (cancel ends it).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from shared.vln_metrics import episode_metrics, euclidean_geodesic
from shared import keys
from shared.bus.typed import NotFound, TypedBus
from shared.schemas import (
    CancelRequest, Decision, JobCancelled, JobFailed, LoadSceneRequest, JobAccepted, JobEvent,
    JobEventKind, MissionFinished, MissionRequest, MissionStarted, JobState, MissionStep, Pose, SceneSummary,
    UsageData,
)


# Fixed per-step stage timings, so the evaluation's cost ledger can be checked exactly.
SCRIPTED_TIMINGS_S = {"observe_s": 0.01, "candidates_s": 0.02, "anticipation_s": 0.03, "spatial_map_s": 0.04,
                      "decide_s": 0.05, "move_s": 0.06, "prompt_ready_s": 0.1}


class ScriptedRobotIo:
    """Serves ``IO_LOAD_SCENE``; ``loaded`` lists the scenes in the order they were loaded."""

    def __init__(self, bus: TypedBus, robot: str = "robot0"):
        self.loaded: list[str] = []
        self._entities = [bus.serve(keys.IO_LOAD_SCENE.format(robot=robot), LoadSceneRequest, self._load)]

    def _load(self, req: LoadSceneRequest) -> SceneSummary:
        if "broken" in req.scene:
            raise ValueError(f"{req.scene}: cannot be read")
        self.loaded.append(req.scene)
        return SceneSummary(scene=req.scene, bounds_min_m=(-10, -10, 0), bounds_max_m=(10, 10, 3),
                            reachable_area_m2=100.0)

    def close(self) -> None:
        for e in self._entities:
            e.close()


class ScriptedNavPlanner:
    """Serves ``MISSION_SUBMIT``/``MISSION_CANCEL`` with a straight-line walker (one mission at a time
    per thread). ``requests`` keeps every accepted :class:`MissionRequest`; ``steps_walked`` counts the steps of
    every mission (a test's clock can move with it)."""

    def __init__(self, bus: TypedBus, robot: str = "robot0", *, step_m: float = 1.0, step_interval_s: float = 0.0):
        self.bus, self.robot, self.step_m, self.interval_s = bus, robot, step_m, step_interval_s
        self.requests: list[MissionRequest] = []
        self.steps_walked = 0
        self._steps_lock = threading.Lock()
        self._cancel: dict[str, threading.Event] = {}
        self._threads: list[threading.Thread] = []
        self._entities = [
            bus.serve(keys.MISSION_SUBMIT.format(robot=robot), MissionRequest, self._submit),
            bus.serve(keys.MISSION_CANCEL.format(robot=robot), CancelRequest, self._cancel_req),
        ]

    def _submit(self, req: MissionRequest) -> JobAccepted:
        self.requests.append(req)
        self._cancel[req.mission_id] = threading.Event()
        t = threading.Thread(target=self._walk, args=(req,), daemon=True)
        self._threads.append(t)
        t.start()
        return JobAccepted(job_id=req.mission_id, accepted=True)

    def _cancel_req(self, req: CancelRequest) -> JobAccepted:
        ev = self._cancel.get(req.mission_id)
        if ev is None:
            raise NotFound(f"no mission {req.mission_id!r}")
        ev.set()
        return JobAccepted(job_id=req.mission_id, accepted=True)

    def _walk(self, req: MissionRequest) -> None:
        mid, opts = req.mission_id, req.options
        key = keys.MISSION_EVENTS.format(robot=self.robot, mission=mid)
        cancel = self._cancel[mid]
        seq = 0

        def emit(kind, state, step, data):
            nonlocal seq
            self.bus.publish(key, JobEvent(job_id=mid, seq=seq, kind=kind, state=state, step=step, data=data))
            seq += 1

        pos = np.array(opts.start_pose.position_m if opts.start_pose else (0.0, 0.0, 0.0), float)
        goal = np.array(opts.goal_m, float) if opts.goal_m is not None else pos.copy()
        traj, lat = [pos.copy()], []
        emit(JobEventKind.STARTED, JobState.RUNNING, 0,
             MissionStarted(pose=Pose(position_m=tuple(pos.tolist())), instruction=req.instruction, map_id=req.map_id,
                            options=opts))
        if "crash" in req.instruction:
            emit(JobEventKind.ERROR, JobState.FAILED, 0, JobFailed(error="scripted crash"))
            return
        if "hang" in req.instruction:
            cancel.wait(60.0)
            emit(JobEventKind.FINISHED, JobState.CANCELLED, 0, JobCancelled())
            return
        stop = False
        for step in range(1, opts.max_steps + 1):
            t0 = time.perf_counter()
            if cancel.wait(self.interval_s) if self.interval_s else cancel.is_set():
                emit(JobEventKind.FINISHED, JobState.CANCELLED, step - 1, JobCancelled())
                return
            d = goal - pos
            dist = float(np.linalg.norm(d))
            stop = dist < 1e-9
            if not stop:
                pos = pos + d * min(1.0, self.step_m / dist)
                traj.append(pos.copy())
            lat.append(time.perf_counter() - t0 + 0.01)
            with self._steps_lock:
                self.steps_walked += 1
            emit(JobEventKind.STEP, JobState.RUNNING, step,
                 MissionStep(pose=Pose(position_m=tuple(pos.tolist())), candidates=[], decision=Decision(
                     candidate_index=0, kind="stop" if stop else "waypoint", backend=opts.policy,
                     reasoning="stop at the goal" if stop else "towards the goal",
                     prompt_tokens=100, completion_tokens=10, cost_usd=0.0005),
                 timings_s=dict(SCRIPTED_TIMINGS_S)))
            if stop:
                break
        m = episode_metrics(np.array(traj), goal, geodesic=euclidean_geodesic, stop_called=stop,
                            reference_path_m=opts.reference_path_m)
        steps = len(lat)
        emit(JobEventKind.FINISHED, JobState.SUCCEEDED if stop else JobState.FAILED, steps,
             MissionFinished(stop_called=stop, steps=steps, error="" if stop else "step budget exhausted",
                             trajectory_m=[tuple(p) for p in np.array(traj).tolist()], metrics=m.to_dict(),
                             usage=UsageData(calls=steps, prompt_tokens=100 * steps, completion_tokens=10 * steps,
                                             cost_usd=0.0005 * steps),
                             step_latency_s=[round(x, 4) for x in lat]))

    def close(self) -> None:
        for ev in self._cancel.values():
            ev.set()
        for e in self._entities:
            e.close()
        for t in self._threads:
            t.join(5.0)
