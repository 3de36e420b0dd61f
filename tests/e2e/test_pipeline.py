"""The main job end to end over real processes: explore -> reconstruct -> navigate, via the gateway.

Also checks what a user relies on afterwards: the map is listed and downloadable, the mission's
events are complete (gap-free), its pictures are served, and all of it survives a gateway crash.
"""

import os
import signal
import time

import httpx
import pytest

from deploy.demo import make_episode, wait_job

pytestmark = [pytest.mark.e2e, pytest.mark.system]

# A small house explored to the end (no step budget): 5 regions, where the default house has 7-9 tours to
# record and reconstruct; what the test checks does not depend on the house's size.
SCENE = "generated:0:area=80"


@pytest.fixture
def system_here(system_on_scene):
    """The session's launched system (tests/conftest.py) with robot0 on the small house; put back after."""
    with httpx.Client(base_url=system_on_scene.gateway_url, timeout=30) as http:
        r = http.post("/robot/scene", json={"scene": SCENE}, timeout=180)
        assert r.status_code == 200, r.text
        yield system_on_scene, http


def test_explore_reconstruct_navigate_and_survive_a_gateway_crash(system_here):
    launcher, http = system_here
    job = http.post("/explorations", json={"map_id": "e2e-house"})
    assert job.status_code == 202, job.text
    rec = wait_job(http, job.json()["url"], 400, lambda r: None)
    assert rec["state"] == "succeeded", rec.get("error")
    info = http.get("/maps/e2e-house").json()
    assert info["point_count"] > 100_000 and info["regions"] >= 3 and info["has_labels"]
    # Listed beside the maps other tests of the shared system stored, and only once.
    assert [m["map_id"] for m in http.get("/maps").json()].count("e2e-house") == 1

    ep = make_episode(SCENE, seed=3)
    options = {"policy": "oracle", "max_steps": 8, "start_pose": ep.start_pose.model_dump(),
               "goal_m": list(map(float, ep.goal_m)),
               "reference_path_m": [list(map(float, p)) for p in ep.reference_path_m]}
    mission = http.post("/missions", json={"instruction": ep.instruction, "map_id": "e2e-house", "options": options})
    assert mission.status_code == 202, mission.text
    mid = mission.json()["id"]
    rec = wait_job(http, f"/missions/{mid}", 300, lambda r: None)
    assert rec["state"] in ("succeeded", "failed") and rec["step"] >= 1
    assert rec["metrics"] is not None and "ndtw" in rec["metrics"] and len(rec["trajectory"]) >= 2
    events = http.get(f"/missions/{mid}/history").json()
    seqs = [e["seq"] for e in events]
    assert seqs == list(range(len(seqs))) and events[0]["kind"] == "started" and events[-1]["kind"] == "finished"
    step = next(e for e in events if e["kind"] == "step")
    img = http.get(f"/missions/{mid}/events/{step['seq']}/images/map.jpg")
    assert img.status_code == 200 and img.content[:2] == b"\xff\xd8"

    # A gateway crash loses nothing: the supervisor restarts it and the record is the same.
    gw = launcher.proc("gateway-0")
    restarts = gw.restarts  # the shared system's gateway may have been restarted before
    os.kill(gw.popen.pid, signal.SIGKILL)
    end = time.monotonic() + 60
    while time.monotonic() < end:
        try:
            if http.get(f"/missions/{mid}").status_code == 200:
                break
        except httpx.TransportError:
            pass
        time.sleep(0.5)
    assert http.get(f"/missions/{mid}").json()["state"] == rec["state"]
    assert [e["seq"] for e in http.get(f"/missions/{mid}/history").json()] == seqs
    assert gw.restarts > restarts
