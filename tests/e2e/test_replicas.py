"""Two renderer processes share render requests through zenoh; killing one loses no request.

The renderers are real processes behind a real router (deploy.launcher); the map store is the
scripted reconstructor, on a zenoh session in this process.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from deploy.launcher import Launcher
from tests.doubles.scripted_services import ScriptedReconstructor
from shared import keys
from shared.bus.typed import TypedBus
from shared.bus.zenoh_bus import ZenohBus
from shared.schemas import CameraIntrinsics, Ping, RenderRequest, RenderResult, ServiceMetrics, ViewPose

pytestmark = [pytest.mark.e2e, pytest.mark.system]

N_REQUESTS = 200
CAMERA = CameraIntrinsics(width_px=48, height_px=48, hfov_deg=90.0)


def render_request(i: int) -> RenderRequest:
    heading = 2 * math.pi * i / N_REQUESTS
    return RenderRequest(map_id="house", views=[ViewPose(position_m=(0.0, 0.0, 0.0), heading_rad=heading)],
                         camera=CAMERA, with_labels=False)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """Two renderers (renderer-0, renderer-1), a map source and a client on the launcher's router, for the
    whole module (three starts cost seconds each): the tests read counters as differences, and the one
    that kills a renderer comes last."""
    tmp_path = tmp_path_factory.mktemp("replicas")
    launcher = Launcher(tmp_path, replicas={"renderer": 2}, services=["renderer"], restart=False)
    with launcher:
        # The map source plays the reconstructor: it joins as that user, so the ACL lets it serve maps.
        bus = ZenohBus(launcher.client_settings("reconstructor"))
        maps = ScriptedReconstructor(TypedBus(bus, "reconstructor"))
        maps.add_random("house", 20_000, seed=3)
        # The client asks for views (the planner's right) and every instance's metrics (the gateway's):
        # under the least-privilege ACL only the read-only operator may do both, not the map source.
        op_bus = ZenohBus(launcher.client_settings())
        client = TypedBus(op_bus, "test")
        try:
            yield launcher, client
        finally:
            client.close()
            op_bus.close()
            maps.close()
            bus.close()


def views_served(client: TypedBus, instance: str) -> int:
    m = client.request(keys.METRICS.format(service="renderer", instance=instance), Ping(), ServiceMetrics,
                       timeout_s=5.0)
    return m.endpoints["views"].requests if "views" in m.endpoints else 0


def send_all(client: TypedBus, on_done=None) -> list[RenderResult]:
    """N_REQUESTS balanced requests, 4 in flight at a time (bounded: every call has a timeout)."""

    def one(i: int) -> RenderResult:
        out = client.request(keys.RENDER_VIEWS.format(), render_request(i), RenderResult, timeout_s=20.0,
                             balance="renderer")
        if on_done:
            on_done()
        return out

    with ThreadPoolExecutor(4) as pool:
        return list(pool.map(one, range(N_REQUESTS), timeout=240))


def check(results: list[RenderResult]) -> None:
    assert len(results) == N_REQUESTS
    for r in results:
        assert r.map_id == "house" and r.rgb.shape == (1, CAMERA.height_px, CAMERA.width_px, 3)
    # different headings see different parts of the map: the answers are real renders, not one cached reply
    assert len({r.rgb.tobytes() for r in results}) > N_REQUESTS // 2


def test_two_renderers_share_200_requests_and_none_is_lost(cluster):
    launcher, client = cluster
    assert launcher.alive() == {"renderer": 2}
    before = {i: views_served(client, i) for i in ("renderer-0", "renderer-1")}
    t0 = time.perf_counter()
    results = send_all(client)
    elapsed = time.perf_counter() - t0
    check(results)
    served = {i: views_served(client, i) - before[i] for i in before}
    assert sum(served.values()) == N_REQUESTS, served  # each request answered exactly once
    assert min(served.values()) >= N_REQUESTS // 4, f"one replica idled: {served}"
    print(f"\n200 requests in {elapsed:.1f} s over 2 renderers: {served}")


def test_container_healthcheck_sees_a_live_instance_through_the_router(cluster):
    launcher, _ = cluster
    env = launcher.client_env()

    def check(*args):
        return subprocess.run([sys.executable, "-m", "deploy.healthcheck", *args], env=env, capture_output=True,
                              text=True, timeout=60)

    assert check("renderer", "--instance", "renderer-1").returncode == 0
    assert check("router").returncode == 0
    missing = check("planner", "--any", "--timeout-s", "1")
    assert missing.returncode == 1 and "no planner instance alive" in missing.stderr


def test_killing_a_renderer_midway_still_answers_every_request(cluster):
    launcher, client = cluster
    assert launcher.alive() == {"renderer": 2}
    survivor_before = views_served(client, "renderer-0")
    done = 0
    lock = threading.Lock()
    kill_at = N_REQUESTS // 4
    killed = threading.Event()

    def on_done():
        nonlocal done
        with lock:
            done += 1
            if done == kill_at and not killed.is_set():
                killed.set()
                launcher.proc("renderer-1").popen.kill()  # SIGKILL: no goodbye, no undeclaration

    results = send_all(client, on_done)
    assert killed.is_set()
    assert launcher.proc("renderer-1").popen.wait(10) == -9
    check(results)
    # the survivor took over everything after the kill; the dead one's token is gone
    assert views_served(client, "renderer-0") - survivor_before >= N_REQUESTS - kill_at
    deadline = time.monotonic() + 10
    while launcher.alive().get("renderer", 0) != 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert launcher.alive() == {"renderer": 1}
