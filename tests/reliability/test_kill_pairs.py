"""Kill pairs (issue 15, item 5), for real: SIGKILL the gateway and the planner *together* while a
mission runs. The launcher restarts both; the restarted gateway reconciles the mission with the live
(restarted) planner, which never heard of it, and fails it with the reason - it is never left running,
and it no longer blocks ``POST /robot/scene``."""

from __future__ import annotations

import os
import signal

import httpx
import pytest

from tests.reliability.conftest import MAP_ID, SCENE, wait_until

pytestmark = pytest.mark.e2e

TERMINAL = ("succeeded", "failed", "cancelled")


def test_killing_the_gateway_and_the_planner_together_leaves_no_stuck_mission(system, tally):
    with httpx.Client(base_url=system.gateway_url, timeout=30) as http:
        wait_until(lambda: http.get("/health").status_code == 200, 60, "gateway up")
        r = http.post("/missions", json={"instruction": "Walk through every room and stop in the kitchen.",
                                         "map_id": MAP_ID, "options": {"max_steps": 300}})
        assert r.status_code == 202, r.text
        mission = r.json()["id"]
        wait_until(lambda: http.get(f"/missions/{mission}").json()["step"] >= 1, 120, "mission under way")
        procs = [system.proc("gateway-0"), system.proc("planner-0")]
        before = [p.restarts for p in procs]
        for p in procs:
            os.kill(p.popen.pid, signal.SIGKILL)
        tally.add("faults_injected", 2)
        tally.add("kill_pairs")
        wait_until(lambda: all(p.restarts > b for p, b in zip(procs, before)), 60, "both restarted")
        system.wait_alive(120)
        tally.add("faults_survived", 2)
        rec = wait_until(lambda: (x := http.get(f"/missions/{mission}").json())["state"] in TERMINAL and x, 90,
                         "the orphaned mission reconciled")
        tally.add("stuck_missions", 0 if rec["state"] in TERMINAL else 1)
        assert rec["state"] == "failed" and "planner" in rec["error"], rec
        # Nothing is left running, so the scene can be switched (evaluation runs can go on).
        assert http.get("/missions", params={"state": ["running", "queued"]}).json()["total"] == 0
        assert http.post("/robot/scene", json={"scene": SCENE}).status_code == 200
