"""The launched system the suite shares: a router and every service as OS processes (deploy.launcher),
supervised, with one map imported from the scene robot-io simulates.

Starting it costs tens of seconds of CPU (seven interpreters, robot-io's house and nav grids, the map
import), and tests/e2e and tests/reliability used to start about a dozen of them; one per session is
started by the ``system`` fixture (tests/conftest.py) for every test that does not need a system of a
different shape. Tests that kill a process rely on the supervisor bringing it back; tests that switch a
robot's scene (the evaluation runner does) use ``system_on_scene`` (tests/conftest.py), which leaves nothing
running, and every robot is put back on ``SCENE`` before a test that uses ``system`` itself, so such a test
finds the system as the fixture made it.
"""

from __future__ import annotations

import concurrent.futures
import functools
import json
from pathlib import Path

import httpx

from tests import waiting

SCENE = "generated:0"
MAP_ID = "rel-house"
# Two robots (robot0, robot1: a robot-io and a gateway each, the other services shared): the evaluation
# budget test runs both lanes at once; every other test talks to robot0's gateway (``gateway_url``).
ROBOTS = 2


def wait_until(pred, timeout_s: float, what: str, interval_s: float = 0.1):
    """tests.waiting.wait_until, where a gateway that is down or restarting means "not yet"."""
    return waiting.wait_until(pred, timeout_s, what, interval_s=interval_s, ignore=(httpx.HTTPError, OSError))


@functools.lru_cache(maxsize=1)
def _sim_scene():
    """The scene robot-io simulates and its walkable viewpoints, built once per session: four fixtures and
    tests sample it, and the default house and its nav grids cost seconds to build (read-only here)."""
    from evaluation.clouds import walkable_viewpoints
    from services.robot_io.core import ROBOTS as BACKENDS

    with BACKENDS.create("sim", {"scene": SCENE}) as robot:
        return robot.scene, walkable_viewpoints(robot.scene)


def scene_ply(density_per_m2: float = 60.0) -> bytes:
    """A PLY of points sampled from the scene robot-io simulates (the map a mission runs on)."""
    from evaluation.clouds import sample_scene_cloud
    from shared.cloud import encode

    scene, viewpoints = _sim_scene()
    return encode(sample_scene_cloud(scene, density_per_m2=density_per_m2, max_points=200_000,
                                     viewpoints_m=viewpoints))


def launch(run_dir: Path):
    """The shared system, started and with ``MAP_ID`` imported (a context manager: the launcher)."""
    from deploy.launcher import Launcher

    env = {
        "ANT_ROBOT_CONFIG": json.dumps({"scene": SCENE}),
        "ANT_STORE_DIR": str(run_dir / "maps"),
        "ANT_DB_PATH": str(run_dir / "gateway.sqlite3"),
        "ANT_LOG_LEVEL": "WARNING",
    }
    launcher = Launcher(run_dir, extra_env=env, restart=True, robots=ROBOTS)
    launcher.run_dir_path = run_dir
    # The map's cloud is sampled here (the house, its nav grids and viewpoints: seconds) while the
    # launcher's processes start, rather than after they are all up; import_map waits for it.
    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="map-ply")
    launcher.map_ply = pool.submit(scene_ply)
    pool.shutdown(wait=False)  # the one job still runs; its thread ends with it
    return launcher


def import_map(launcher) -> None:
    with httpx.Client(base_url=launcher.gateway_url, timeout=120) as http:
        wait_until(lambda: http.get("/maps").status_code == 200, 60, "gateway reaches the reconstructor")
        r = http.post("/maps", params={"map_id": MAP_ID, "filename": "scene.ply"}, content=launcher.map_ply.result(),
                      headers={"Content-Type": "application/octet-stream"})
        assert r.status_code == 201, r.text


def cancel_left_running(launcher) -> None:
    """Nothing left running on any robot of the shared system (a mission a test left running would
    change what the next test finds)."""
    for url in launcher.gateway_urls:
        with httpx.Client(base_url=url, timeout=180) as http:
            wait_until(lambda: http.get("/health").status_code == 200, 60, f"gateway {url} up")
            running = http.get("/missions", params={"state": ["running", "queued"]}).json()
            for m in running["items"]:
                http.post(f"/missions/{m['id']}/cancel")
            wait_until(lambda: http.get("/missions", params={"state": ["running", "queued"]}).json()["total"] == 0,
                       120, f"no mission left running on {url}")


def put_back(launcher, scene: str = SCENE) -> None:
    """Every robot of the shared system on ``scene``, with nothing left running."""
    cancel_left_running(launcher)
    for url in launcher.gateway_urls:
        with httpx.Client(base_url=url, timeout=180) as http:
            # A robot already on it is left as it stands (a reload rebuilds the house and its nav grids:
            # seconds of CPU, and the tests that follow never relied on a robot's pose).
            if http.get("/robot/scene").json()["scene"] != scene:
                wait_until(lambda: http.post("/robot/scene", json={"scene": scene}).status_code == 200, 120,
                           f"robot of {url} back on {scene}", interval_s=0.5)
