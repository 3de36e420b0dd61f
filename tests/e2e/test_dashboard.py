"""The dashboard in a real headless Chromium: submit a mission, watch its steps appear.

The gateway runs under uvicorn on 127.0.0.1 over a real zenoh bus; a scripted planner, mapper and
reconstructor answer on a second zenoh session. A second test explores a new map from the dashboard. Needs Debian's ``chromium`` and the ``playwright``
package (no downloaded browser); skipped where either is missing.
"""

from __future__ import annotations

import logging
import shutil
import threading
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from tests.waiting import wait_until

from deploy.launcher import free_port
from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from tests.e2e.browser import headless_chromium, open_dashboard
from tests.doubles.scripted_services import ScriptedMapper, ScriptedPlanner, ScriptedReconstructor
from shared.bus.config import ZenohSettings
from shared.bus.typed import TypedBus

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]


@contextmanager
def serve_gateway(tmp_path, maps=None, **overrides):
    """The gateway under uvicorn over zenoh, scripted services behind it; yields its URL. ``maps``: called
    with the scripted reconstructor to add more maps."""
    uvicorn = pytest.importorskip("uvicorn")
    from shared.bus.zenoh_bus import ZenohBus

    zport, hport = free_port(), free_port()
    services_bus = ZenohBus(ZenohSettings(listen=[f"tcp/127.0.0.1:{zport}"]))
    typed = TypedBus(services_bus, "scripted")
    recon = ScriptedReconstructor(typed)
    recon.add_random("demo-house", 20_000)
    if maps is not None:
        maps(recon)
    # A step every 0.3 s (was 0.6): the page must see the first step while the mission still runs, and
    # five steps after it leave it 1.5 s of wall time to be read as running; each mission of this file
    # (two tests) waited 3.6 s for its six steps, 1.8 s now.
    planner = ScriptedPlanner(typed, steps=6, step_interval_s=0.3, candidates=3, image_px=128)
    mapper = ScriptedMapper(typed, stages=3, stage_interval_s=0.5, reconstructor=recon)
    settings = GatewaySettings(instance="gw-e2e", host="127.0.0.1", port=hport, db_path=tmp_path / "gw.sqlite3",
                               zenoh=ZenohSettings(connect=[f"tcp/127.0.0.1:{zport}"]), request_timeout_s=5.0,
                               **overrides)
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=hport, log_config=None,
                                           timeout_graceful_shutdown=2))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{hport}"
    auth = {"Authorization": f"Bearer {settings.read_token}"} if settings.read_token else {}

    def ready():
        try:
            # Ready once the gateway answers and reaches the reconstructor over zenoh.
            return httpx.get(f"{url}/maps", timeout=2, headers=auth).status_code == 200
        except httpx.HTTPError:
            return False

    try:
        wait_until(ready, 30, "gateway up and connected")
        yield url
    finally:
        server.should_exit = True
        thread.join(10)
        planner.close()
        mapper.close()
        recon.close()
        services_bus.close()


@pytest.fixture
def live_gateway(tmp_path):
    with serve_gateway(tmp_path) as url:
        yield url


def test_dashboard_submits_a_mission_and_shows_its_steps_live(live_gateway, tmp_path):
    with headless_chromium() as browser:
        page, errors = open_dashboard(browser, live_gateway)
        page.fill("#instruction", "Walk through the hallway into the kitchen and stop next to the fridge.")
        page.click("#submit")
        # Steps arrive live over SSE: the first while the mission still runs ...
        page.wait_for_selector("#steps li[data-seq='1']", timeout=15_000)
        assert page.text_content("#m-state") == "running"
        # ... then the rest, with pictures, candidates and the decision's reasoning.
        page.wait_for_selector("#m-state.succeeded", timeout=30_000)
        page.wait_for_function("document.querySelector('#panorama').naturalWidth > 0", timeout=10_000)
        page.wait_for_function(
            "[...document.querySelectorAll('.cand img')].every(i => i.complete && i.naturalWidth > 0)",
            timeout=10_000)
        steps = page.locator("#steps li").count()
        cards = page.locator(".cand").count()
        reasoning = page.text_content("#decision .reason")
        shot = page.screenshot(full_page=True)
    assert steps == 8  # started, 6 steps, finished
    assert cards == 3
    assert "stop" in (reasoning or "").lower()
    assert not errors, errors
    (tmp_path / "dashboard.png").write_bytes(shot)
    out = REPO / "runs" / "screenshots"
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(tmp_path / "dashboard.png", out / "dashboard.png")
    # And what the browser saw is what the API kept.
    record = httpx.get(f"{live_gateway}/missions?limit=1", timeout=5).json()["items"][0]
    assert record["state"] == "succeeded" and record["step"] == 6


def test_dashboard_explores_a_new_map_with_progress(live_gateway):
    with headless_chromium() as browser:
        page, errors = open_dashboard(browser, live_gateway)
        page.fill("#explore-map", "explored-house")
        page.click("#explore")
        # Progress arrives over SSE while the exploration runs (stages 0.5 s apart) ...
        page.wait_for_function("document.querySelector('#explore-status').dataset.state === 'running'"
                               " && document.querySelector('#explore-progress').value > 0", timeout=15_000)
        assert page.is_disabled("#explore")
        # ... and at the end the new map is offered to the mission form.
        page.wait_for_function("document.querySelector('#explore-status').dataset.state === 'succeeded'",
                               timeout=20_000)
        page.wait_for_selector("#map-select option[value='explored-house']", state="attached", timeout=10_000)
        progress = page.eval_on_selector("#explore-progress", "e => e.value")
        status = page.text_content("#explore-status")
        selected = page.eval_on_selector("#map-select", "e => e.value")
        enabled = not page.is_disabled("#explore")
        shot = page.screenshot(full_page=True)
    assert progress == 1 and status.startswith("succeeded 100%")
    assert selected == "explored-house" and enabled
    assert not errors, errors
    out = REPO / "runs" / "screenshots"
    out.mkdir(parents=True, exist_ok=True)
    (out / "dashboard-explore.png").write_bytes(shot)
    explorations = httpx.get(f"{live_gateway}/explorations", timeout=5).json()["items"]
    assert [(x["map_id"], x["state"]) for x in explorations] == [("explored-house", "succeeded")]


def test_dashboard_cancels_a_running_exploration_from_another_page(live_gateway):
    """One page starts an exploration; a page opened later shows it running (the explore box follows an
    open exploration) and cancels it; both pages then show it cancelled, with the stage it stopped in."""
    status = "document.querySelector('#explore-status')"
    with headless_chromium() as browser:
        first, errors = open_dashboard(browser, live_gateway)
        # A map id with "hang": the scripted mapper holds in its last stage until the exploration is cancelled.
        first.fill("#explore-map", "hang-house")
        first.click("#explore")
        first.wait_for_function(f"{status}.textContent.includes('reconstructing')", timeout=15_000)
        second, more_errors = open_dashboard(browser, live_gateway)
        second.wait_for_function(f"{status}.textContent.includes('reconstructing')", timeout=15_000)
        assert second.is_disabled("#explore") and second.is_visible("#explore-cancel")
        second.click("#explore-cancel")
        for page in (first, second):
            page.wait_for_function(f"{status}.dataset.state === 'cancelled'", timeout=15_000)
        texts = [p.text_content("#explore-status") for p in (first, second)]
        hidden = [p.is_hidden("#explore-cancel") for p in (first, second)]
        enabled = [not p.is_disabled("#explore") for p in (first, second)]
        options = first.eval_on_selector_all("#map-select option", "os => os.map(o => o.value)")
        shot = first.screenshot(full_page=True)
    out = REPO / "runs" / "screenshots"
    out.mkdir(parents=True, exist_ok=True)
    (out / "dashboard-explore-cancelled.png").write_bytes(shot)
    assert not errors and not more_errors, errors + more_errors
    assert all(t.startswith("cancelled") and t.endswith("while reconstructing") for t in texts), texts
    assert all(hidden) and all(enabled) and "hang-house" not in options
    (rec,) = httpx.get(f"{live_gateway}/explorations", timeout=5).json()["items"]
    assert rec["state"] == "cancelled" and rec["stage"] == "reconstructing" and rec["map_id"] == "hang-house"


def test_dashboard_with_a_read_token_sends_it_on_every_read_and_its_steps_agree(tmp_path, caplog):
    """With ANT_READ_TOKEN set, the page takes the token from a #token= link, sends it on every fetch,
    EventSource, image and download (none is refused), keeps it out of the address bar and the access
    log; and the header, the decision and the step list count the same steps."""
    caplog.set_level(logging.INFO, logger="uvicorn.access")
    secret = "api-secret-4711"
    with serve_gateway(tmp_path, read_token="read-secret-0815", api_token=secret) as url, \
            headless_chromium() as browser:
        refused: list[str] = []
        page, errors = open_dashboard(browser, url, fragment=f"token={secret}",
                                      on_response=lambda r: refused.append(r.url) if r.status == 401 else None)
        address = page.evaluate("location.href")
        page.fill("#instruction", "Walk through the hallway into the kitchen and stop next to the fridge.")
        page.click("#submit")
        page.wait_for_selector("#m-state.succeeded", timeout=30_000)
        page.wait_for_function("document.querySelector('#panorama').naturalWidth > 0", timeout=10_000)
        page.wait_for_function(
            "[...document.querySelectorAll('.cand img')].every(i => i.complete && i.naturalWidth > 0)",
            timeout=10_000)
        header = page.text_content("#m-step")
        choice = page.text_content("#decision .choice")
        last_step = page.locator("#steps li .k").filter(has_text="step").last.text_content()
        download = page.get_attribute("#m-downloads a", "href") or ""
        shot = page.screenshot(full_page=True)
    out = REPO / "runs" / "screenshots"
    out.mkdir(parents=True, exist_ok=True)
    (out / "dashboard_read_token.png").write_bytes(shot)
    assert not refused, refused
    assert not errors, errors
    assert secret not in address and "#token" not in address
    # Six decisions: the header, the last decision and the list say the same.
    assert header == "step 6" and choice.startswith("Step 6:") and last_step == "step 6", (header, choice, last_step)
    assert "access_token=" in download
    access = "\n".join(r.getMessage() for r in caplog.records if r.name == "uvicorn.access")
    assert "access_token=***" in access and secret not in access
