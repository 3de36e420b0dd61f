"""The mission loop (Section 4.3) on the real simulator and renderer core, with bad inputs from its ports:
a waypoint predictor that finds nothing (agent boxed in), a way back that is blocked, and an LLM that
times out or answers garbage. Every mission ends with a clear outcome, never a crash or a hang."""

from __future__ import annotations

import numpy as np
import pytest

from services.mapper.core import PREDICTORS
from services.planner.core import POLICIES, OpenAIConfig
from services.planner.core.mission import MissionLoop, MissionOutcome
from services.planner.core.policy import Policy
from services.renderer.core import MapRenderer, SpatialMapper
from services.robot_io.core import ROBOTS
from libs.pointrender import RENDERERS, IndexedCloud
from shared.schemas import CandidateKind, JobEventKind, JobState, MissionEnd, MissionOptions, MoveResult, MoveStatus
from tests.unit.planner.test_planner_openai import FakeChatServer

pytestmark = pytest.mark.timeout(60)

CAM = {"width_px": 64, "height_px": 64, "hfov_deg": 90.0}


@pytest.fixture(scope="module")
def world(house_map_cloud):
    """The real SimRobot in a generated house and a MapRenderer over a cloud sampled from its mesh."""
    robot = ROBOTS.create("sim", {"scene": "generated:0", "camera": CAM})
    c = house_map_cloud  # the same scene's cloud, sampled once for the session
    renderer = RENDERERS.create("numpy")
    port = MapRenderer(IndexedCloud(c), renderer, SpatialMapper())
    yield robot, port, c.label_names
    robot.close()


class NoCandidates:
    """A waypoint predictor that finds no way forward from ``after_step`` on (real ones before)."""

    def __init__(self, after_step: int = 0):
        self.after_step, self.calls, self.inner = after_step, 0, PREDICTORS.create("geometric")

    def predict(self, pano):
        self.calls += 1
        return self.inner.predict(pano) if self.calls <= self.after_step else []


class Scripted(Policy):
    """Records what it was offered; takes the first waypoint, else backtrack, else stop."""

    name = "scripted"

    def __init__(self):
        super().__init__()
        self.offered: list[list[CandidateKind]] = []

    def decide(self, ctx):
        kinds = [c.kind for c in ctx.candidates]
        self.offered.append(kinds)
        for want in (CandidateKind.WAYPOINT, CandidateKind.BACKTRACK, CandidateKind.STOP):
            if want in kinds:
                return self._decision(ctx, ctx.candidates[kinds.index(want)].index, f"take {want.value}")
        raise AssertionError("stop must always be offered")


class Events:
    def __init__(self):
        self.items: list[tuple] = []

    def __call__(self, kind, state, **kw):
        self.items.append((kind, state, kw))


def _run(world, predictor, policy, robot=None, max_steps=6, **opts) -> tuple[MissionOutcome, Events]:
    sim, port, names = world
    sim.reset()
    events = Events()
    loop = MissionLoop(robot=robot or sim, predictor=predictor, renderer=port, policy=policy, emit=events,
                       label_names=names)
    return loop.run("m-bad", "walk to the kitchen and stop", "local", MissionOptions(max_steps=max_steps, **opts)), \
        events


def test_zero_candidates_from_the_start_offers_only_stop_and_ends_with_a_reason(world):
    policy = Scripted()
    out, events = _run(world, NoCandidates(), policy)
    assert policy.offered == [[CandidateKind.STOP]]  # no previous node: no backtrack either
    assert out.state == JobState.SUCCEEDED and out.stop_called and out.steps == 1
    assert "boxed in" in out.reason and "step 0" in out.reason
    assert out.end == MissionEnd.NO_WAY_TO_MOVE  # what MissionFinished.outcome carries
    assert out.trajectory_m.shape == (1, 3)
    assert [e[0] for e in events.items] == [JobEventKind.STARTED, JobEventKind.STEP]


def test_zero_candidates_after_a_move_offers_backtrack_then_stop(world):
    policy = Scripted()
    out, _ = _run(world, NoCandidates(after_step=1), policy)
    assert policy.offered[0][0] == CandidateKind.WAYPOINT
    assert policy.offered[1] == [CandidateKind.BACKTRACK, CandidateKind.STOP]
    assert policy.offered[2] == [CandidateKind.STOP]
    assert out.state == JobState.SUCCEEDED and out.steps == 3 and "boxed in" in out.reason
    # Backtrack went back to the start node.
    assert np.linalg.norm(out.trajectory_m[-1, :2] - out.trajectory_m[0, :2]) < 0.3
    assert np.linalg.norm(out.trajectory_m[1, :2] - out.trajectory_m[0, :2]) > 0.3


class BlockedAfterFirstMove:
    """The real robot, except that every move after the first goes nowhere (a door slammed shut)."""

    def __init__(self, robot):
        self.robot, self.moves = robot, 0

    def __getattr__(self, name):
        return getattr(self.robot, name)

    def move_to(self, dx_m, dy_m):
        self.moves += 1
        if self.moves == 1:
            return self.robot.move_to(dx_m, dy_m)
        return MoveResult(status=MoveStatus.BLOCKED, pose=self.robot.pose, travelled_m=0.0, steps=0)


def test_a_blocked_way_back_is_not_offered_again(world):
    policy = Scripted()
    robot = BlockedAfterFirstMove(world[0])
    out, _ = _run(world, NoCandidates(after_step=1), policy, robot=robot, max_steps=10)
    assert policy.offered[1] == [CandidateKind.BACKTRACK, CandidateKind.STOP]
    assert policy.offered[2] == [CandidateKind.STOP]  # the backtrack went nowhere: not offered again
    assert out.steps == 3 and out.stop_called and "boxed in" in out.reason and robot.moves == 2


def test_a_free_stop_has_no_reason(world):
    class StopNow(Scripted):
        def decide(self, ctx):
            return self._decision(ctx, ctx.stop_candidate.index, "here")

    out, _ = _run(world, PREDICTORS.create("geometric"), StopNow())
    assert out.stop_called and out.reason == "" and out.state == JobState.SUCCEEDED
    assert out.end == MissionEnd.POLICY_STOPPED


def test_step_budget_without_stop_fails_with_a_reason(world):
    class NeverStop(Scripted):
        def decide(self, ctx):
            movable = [c for c in ctx.candidates if c.kind != CandidateKind.STOP]
            return self._decision(ctx, (movable or ctx.candidates)[0].index, "on")

    out, _ = _run(world, PREDICTORS.create("geometric"), NeverStop(), max_steps=2)
    assert out.state == JobState.FAILED and not out.stop_called and "budget of 2" in out.reason
    assert out.end == MissionEnd.MAX_STEPS


# --- an LLM that times out or answers garbage ---------------------------------------------------------------


def _openai(url, **kw):
    cfg = dict(model="gpt-5.1", base_url=url, api_key="test", timeout_s=2.0, retries=0, backoff_initial_s=0.01)
    cfg.update(kw)
    return POLICIES.create("openai", OpenAIConfig(**cfg))


def test_llm_timeout_falls_back_to_the_heuristic_every_step_and_the_mission_completes(world):
    steps = 2
    with FakeChatServer([("sleep", 1.0)] * steps * 2) as srv, _openai(srv.url, timeout_s=0.25) as policy:
        out, events = _run(world, PREDICTORS.create("geometric"), policy, max_steps=steps)
        usage = policy.usage
    assert out.state in (JobState.SUCCEEDED, JobState.FAILED) and 1 <= out.steps <= steps
    assert all(d.fallback and "fallback (heuristic)" in d.reasoning and "Timeout" in d.reasoning
               for d in out.decisions)
    assert usage.fallbacks == out.steps and usage.reasks == 0
    assert len(srv.requests) == out.steps  # retries=0: one try per step, no re-ask after a timeout
    step_events = [kw for kind, _, kw in events.items if kind == JobEventKind.STEP]
    assert [e["data"].usage.fallbacks for e in step_events] == list(range(1, out.steps + 1))


def test_llm_timeout_with_stop_fallback_stops_at_once(world):
    with FakeChatServer([("sleep", 1.0)]) as srv, _openai(srv.url, timeout_s=0.25, fallback="stop") as policy:
        out, _ = _run(world, PREDICTORS.create("geometric"), policy, max_steps=5)
    assert out.steps == 1 and out.stop_called and out.decisions[0].fallback
    assert out.decisions[0].kind == CandidateKind.STOP and out.reason == ""
    assert len(srv.requests) == 1


def test_llm_garbage_is_reasked_once_then_falls_back_and_the_mission_completes(world):
    steps = 2
    script = ["I would go left, probably.", '{"action": "the door"}'] * steps
    with FakeChatServer(script) as srv, _openai(srv.url) as policy:
        out, events = _run(world, PREDICTORS.create("geometric"), policy, max_steps=steps)
        usage = policy.usage
    assert out.state in (JobState.SUCCEEDED, JobState.FAILED) and 1 <= out.steps <= steps
    assert all(d.fallback and "fallback (heuristic)" in d.reasoning for d in out.decisions)
    # Each step paid for the answer and its one re-ask.
    assert usage.reasks == out.steps and usage.calls == 2 * out.steps and usage.fallbacks == out.steps
    assert all(d.prompt_tokens == 2000 for d in out.decisions)
    assert len(srv.requests) == 2 * out.steps
    reask = srv.requests[1]["messages"]
    assert reask[-2] == {"role": "assistant", "content": "I would go left, probably."}
    last = [kw for kind, _, kw in events.items if kind == JobEventKind.STEP][-1]
    assert last["data"].usage.reasks == out.steps


# --- the spatial map is drawn while the views render ---------------------------------------------------------


class Overlapping:
    """The real renderer port, except that the views wait (bounded) until the spatial map has started:
    asked one after the other, each step would wait the whole bound."""

    def __init__(self, port, fail_map: bool = False):
        import threading

        self.port, self.fail_map, self.started = port, fail_map, threading.Event()
        self.waited: list[bool] = []

    def views(self, *a, **kw):
        self.waited.append(self.started.wait(5.0))
        self.started.clear()
        return self.port.views(*a, **kw)

    def spatial_map(self, *a, **kw):
        self.started.set()
        if self.fail_map:
            raise RuntimeError("spatial map: no such floor")
        return self.port.spatial_map(*a, **kw)


def test_the_spatial_map_is_drawn_while_the_views_render_and_its_failure_reaches_the_step(world):
    sim, port, names = world
    for fail in (False, True):
        sim.reset()
        renderer = Overlapping(port, fail_map=fail)
        events = Events()
        loop = MissionLoop(robot=sim, predictor=PREDICTORS.create("geometric"), renderer=renderer, policy=Scripted(),
                           emit=events, label_names=names)
        if fail:
            with pytest.raises(RuntimeError, match="no such floor"):
                loop.run("m-map", "walk on", "local", MissionOptions(max_steps=2))
            continue
        out = loop.run("m-map", "walk on", "local", MissionOptions(max_steps=2))
        assert out.steps == 2 and renderer.waited == [True, True]
        steps = [kw["data"] for kind, _, kw in events.items if kind == JobEventKind.STEP]
        assert all(s.timings_s["spatial_map_s"] > 0 and s.timings_s["anticipation_s"] > 0 for s in steps)
