"""Stuck missions (issue 15, item 5): the planner that ran a mission dies, or restarts and forgets it -
alone or together with the gateway. The gateway reconciles every job that has not ended with the live
workers, by instance and incarnation, at start and periodically: the orphan ends as failed with a
reason, cancelling an orphan succeeds, and ``POST /robot/scene`` is no longer blocked."""

from __future__ import annotations

import pytest

from shared.schemas import JobState
from tests.reliability.live import LIVE_MAP
from tests.waiting import wait_until

# The killed planner's threads fail on its closed session, as a killed process's would (unseen).
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")

TERMINAL = ("succeeded", "failed", "cancelled")
LONG = {"instruction": "Walk through every room of the house and stop in the kitchen.", "map_id": LIVE_MAP,
        "options": {"max_steps": 300}}


def far_goal(live) -> list[float]:
    """The walkable point farthest from the robot: an oracle walk there takes many steps."""
    import numpy as np

    robot = live.service("robot_io").robot
    pts = robot.nav.sample_navigable(np.random.default_rng(0), 400)
    return [float(v) for v in pts[np.argmax(np.linalg.norm(pts[:, :2] - robot.true_pose.xyz[:2], axis=1))]]


def running_mission(client, live) -> str:
    body = {**LONG, "options": {**LONG["options"], "policy": "oracle", "goal_m": far_goal(live)}}
    r = client.post("/missions", json=body)
    assert r.status_code == 202, r.text
    mission = r.json()["id"]
    wait_until(lambda: client.get(f"/missions/{mission}").json()["step"] >= 1, 90, "mission under way")
    return mission


def test_a_mission_whose_planner_restarted_ends_failed_with_the_reason(live, live_gateway, tally):
    with live_gateway(reconcile_interval_s=0.5) as client:
        mission = running_mission(client, live)
        assert client.get(f"/missions/{mission}").json()["state"] == "running"
        live.kill("planner")
        live.start("planner")  # same instance name, a new incarnation that never heard of the mission
        rec = wait_until(lambda: (r := client.get(f"/missions/{mission}").json())["state"] in TERMINAL and r, 30,
                         "the orphan reconciled")
        tally.add("kill_pairs")  # planner killed and restarted under the same name
        tally.add("stuck_missions", 0 if rec["state"] == "failed" else 1)
        # Seen either way round: the old incarnation's token dropping, or the new one's other start time.
        assert rec["state"] == "failed" and "plan-live" in rec["error"], rec
        assert "restarted" in rec["error"] or "went away" in rec["error"], rec
        assert rec["step"] >= 1  # the final event keeps the steps walked
        # Nothing blocks a scene switch any more.
        assert client.get("/missions", params={"state": ["running", "queued"]}).json()["total"] == 0


def test_stale_running_rows_are_failed_when_the_gateway_and_planner_restart_together(live, live_gateway, tally):
    with live_gateway(reconcile_interval_s=60) as client:
        mission = running_mission(client, live)
    # The gateway is gone; its planner dies too, and comes back (a kill pair).
    live.kill("planner")
    live.start("planner")
    with live_gateway(reconcile_interval_s=60) as client:  # same database file
        rec = wait_until(lambda: (r := client.get(f"/missions/{mission}").json())["state"] in TERMINAL and r, 30,
                         "the stale row reconciled at start")
        tally.add("kill_pairs")
        tally.add("stuck_missions", 0 if rec["state"] == "failed" else 1)
        # Either way round, as above: the new incarnation already up ("restarted ... lost it"), or not yet
        # (the old one's token gone: "went away"), which a loaded machine sees when the planner starts slowly.
        assert rec["state"] == "failed" and "plan-live" in rec["error"], rec
        assert "lost it" in rec["error"] or "went away" in rec["error"], rec


def test_cancelling_an_orphan_succeeds_and_a_second_cancel_says_already_cancelled(live, live_gateway, tally):
    with live_gateway(reconcile_interval_s=3600) as client:
        client.app.state.reaper._stop.set()  # no reconciliation: the orphan stays until cancelled
        mission = running_mission(client, live)
        live.kill("planner")
        live.start("planner")
        r = client.post(f"/missions/{mission}/cancel")
        assert r.status_code == 202, r.text
        assert r.json()["state"] == JobState.CANCELLED.value
        rec = client.get(f"/missions/{mission}").json()
        assert rec["state"] == "cancelled" and rec["step"] >= 1
        again = client.post(f"/missions/{mission}/cancel")
        assert again.status_code == 409 and "already cancelled" in again.json()["detail"]
        tally.add("orphans_cancelled")
