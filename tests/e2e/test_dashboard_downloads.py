"""The dashboard's download area in a real headless Chromium: a recorded mission's .rrd and CSV, a map's
PLY / PCD / Nav2 links. Uses the live gateway of :mod:`tests.e2e.test_dashboard` (same skips)."""

from __future__ import annotations

import io
import zipfile

import pytest
import rerun as rr

from tests.e2e.browser import headless_chromium, open_dashboard
from tests.e2e.test_dashboard import REPO, live_gateway  # noqa: F401 - the fixture

pytestmark = pytest.mark.e2e


def test_dashboard_downloads_a_recorded_mission_and_a_map(live_gateway, tmp_path):  # noqa: F811
    with headless_chromium() as browser:
        page, errors = open_dashboard(browser, live_gateway, accept_downloads=True)
        page.fill("#instruction", "Walk into the kitchen and stop.")
        page.check("#record")
        page.click("#submit")
        # While it runs the recording is announced as coming, then offered once it ends.
        page.wait_for_selector("#m-downloads .dl.off", timeout=10_000)
        page.wait_for_selector("#m-state.succeeded", timeout=30_000)
        page.wait_for_selector("#m-downloads a.dl[href$='recording.rrd']", timeout=20_000)
        with page.expect_download() as rrd:
            page.click("#m-downloads a.dl[href$='recording.rrd']")
        rrd.value.save_as(tmp_path / "m.rrd")
        with page.expect_download() as traj:
            page.click("#m-downloads a.dl[href$='trajectory.csv']")
        traj.value.save_as(tmp_path / "t.csv")
        nav2 = page.locator("#maps li", has_text="demo-house").locator("a.dl", has_text="Nav2")
        with page.expect_download() as z:
            nav2.click()
        z.value.save_as(tmp_path / "nav2.zip")
        pcd_href = page.locator("#maps li", has_text="demo-house").locator("a.dl", has_text="PCD").get_attribute("href")
        shot = page.screenshot(full_page=True)
    assert not errors, errors
    entities = {c.entity_path.lstrip("/") for c in rr.chunk.RrdReader(str(tmp_path / "m.rrd")).stream()}
    assert {"world/map", "world/trajectory", "decisions", "views/panorama"} <= entities
    assert (tmp_path / "t.csv").read_text().startswith("step,x_m,y_m,z_m,heading_rad")
    assert sorted(zipfile.ZipFile(io.BytesIO((tmp_path / "nav2.zip").read_bytes())).namelist()) == [
        "demo-house-v1.pgm", "demo-house-v1.yaml"]
    assert pcd_href == "/maps/demo-house/cloud.pcd"
    out = REPO / "runs" / "screenshots"
    out.mkdir(parents=True, exist_ok=True)
    (out / "dashboard-downloads.png").write_bytes(shot)


def test_recording_cli_fetches_and_summarises(live_gateway, tmp_path, capsys):  # noqa: F811
    import httpx

    from shared.recording import main
    from tests.waiting import wait_until

    r = httpx.post(f"{live_gateway}/missions", json={"instruction": "go", "map_id": "demo-house",
                                                    "options": {"record": True}}, timeout=10)
    assert r.status_code == 202, r.text
    mid = r.json()["id"]
    wait_until(lambda: httpx.get(f"{live_gateway}/missions/{mid}", timeout=5).json()["state"] == "succeeded", 30)
    out = tmp_path / "fetched.rrd"
    assert main(["fetch", "--gateway", live_gateway, "--mission", mid, "--out", str(out)]) == 0
    assert main(["summary", str(out)]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and "views/panorama" in printed and "decisions" in printed
    with pytest.raises(SystemExit, match="404"):
        main(["fetch", "--gateway", live_gateway, "--mission", "m-unknown", "--out", str(tmp_path / "x.rrd")])
