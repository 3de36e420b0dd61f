"""Exploration reports where it stands after every panorama: a real robot takes seconds per
panorama and a house hundreds of them, so the exploring stage must show it moves (issue 34).

The job runs as the mapper runs it (a JobRunner on the fake bus) in the box-room world; the robot
cancels it at its n-th panorama, so the test knows exactly how many steps were reported.
"""

from __future__ import annotations

import pytest

from services.mapper.core.explorer import Explorer, ExplorationConfig, ExplorationStep
from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world
from shared.bus import FakeNetwork
from shared.geometry import PinholeCamera
from shared.schemas import ExplorationProgress, JobState
from tests.unit.mapper.test_exploration_cancel import Job, NoBuilds, Robot

STEPS = 9


@pytest.fixture
def net():
    return FakeNetwork()


def test_every_exploration_step_emits_a_progress_event(net):
    job: Job | None = None
    robot = Robot(on_observe=lambda n: n == STEPS and job.cancel())
    job = Job(net, robot, NoBuilds())
    try:
        end = job.end()
    finally:
        job.close()
    assert end.state == JobState.CANCELLED
    steps = [e.data for e in job.events
             if isinstance(e.data, ExplorationProgress) and e.data.stage == "exploring" and e.data.step is not None]
    # One event per panorama taken before the cancel was seen (the loop reports, then checks).
    assert [p.step for p in steps] == list(range(1, STEPS + 1))
    visited = [p.visited for p in steps]
    assert visited == sorted(visited) and visited[0] == 1 and visited[-1] >= STEPS - 2
    assert all(p.seen >= p.visited + p.open_frontiers for p in steps)
    assert all(p.floors == 1 for p in steps)  # the box world is one floor
    assert steps[0].coverage_estimate is not None and all(p.coverage_estimate is not None for p in steps)
    elapsed = [p.elapsed_s for p in steps]
    assert elapsed == sorted(elapsed)
    assert steps[0].time_left_s is None and all(p.time_left_s is not None for p in steps[1:])
    progress = [p.progress for p in steps]
    assert progress == sorted(progress) and 0.02 <= progress[0] and progress[-1] < 0.3
    assert f"{steps[-1].open_frontiers} open frontiers" in steps[-1].message
    assert steps[-1].message.startswith(f"step {STEPS}/")
    # The job's own step counter follows the panoramas (the gateway shows it).
    last = next(e for e in reversed(job.events) if isinstance(e.data, ExplorationProgress) and e.data.step == STEPS)
    assert last.step == STEPS


def test_the_time_left_is_the_step_rate_times_the_open_frontiers():
    seen: list[ExplorationStep] = []
    robot = BoxWorldRobot(rooms_world(), PinholeCamera(48, 48, 90.0))
    res = Explorer(config=ExplorationConfig(max_steps=12)).explore(robot, on_step=seen.append, coverage_every_s=0.0)
    assert len(seen) == res.steps  # one report before each step's budget check, the first after the start panorama
    for st in seen[1:]:
        expected = st.elapsed_s / st.step * min(st.open_frontiers, st.step_budget - st.step)
        assert st.time_left_s == pytest.approx(expected)
        assert 0.0 <= st.coverage_estimate <= 1.0
    # The last report came when the step budget was spent: nothing expected after it.
    assert seen[-1].step == 12 and seen[-1].time_left_s == 0.0
