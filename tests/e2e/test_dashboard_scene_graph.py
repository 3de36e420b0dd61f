"""The dashboard draws the map's scene graph (issue 32): room names at their centroids, openings and
objects, fetched from GET /maps/{id}/scene-graph.json with the read token, in a real headless Chromium.

A labelled cloud sampled from a generated house stands in the scripted reconstructor; its graph is built
by the real builder, as the reconstructor's store builds it. The page exposes what it drew
(``window.sceneGraphProbe``); a screenshot goes to runs/screenshots/dashboard_scene_graph.png."""

from __future__ import annotations

import pytest

from evaluation.clouds import sample_scene_cloud
from libs.scenegraph import build_scene_graph
from libs.scenegraph.text import room_names
from services.robot_io.core import ROBOTS
from shared.cloud import PointCloud
from tests.e2e.browser import headless_chromium, open_dashboard
from tests.e2e.test_dashboard import REPO, serve_gateway

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(180)]


@pytest.fixture(scope="module")
def house() -> PointCloud:
    robot = ROBOTS.create("sim", {"scene": "generated:0"})
    try:
        return sample_scene_cloud(robot.scene, density_per_m2=60.0, max_points=120_000)
    finally:
        robot.close()


def test_dashboard_draws_the_room_names_objects_and_openings_of_the_missions_map(tmp_path, house):
    secret = "read-secret-0815"
    add = lambda recon: recon.add("labelled-house", house.xyz, house.rgb, house.labels,  # noqa: E731
                                  label_names=dict(house.label_names))
    expected = build_scene_graph(house, map_id="labelled-house")
    names = room_names(expected)
    floor0 = sorted(names[r.room_id] for r in expected.rooms if r.floor == 0)
    with serve_gateway(tmp_path, maps=add, read_token=secret) as url, headless_chromium() as browser:
        refused: list[str] = []
        graph_reads: list[int] = []

        def seen(r):
            if r.status == 401:
                refused.append(r.url)
            if "/scene-graph.json" in r.url:
                graph_reads.append(r.status)

        page, errors = open_dashboard(browser, url, fragment=f"token={secret}", on_response=seen)
        page.wait_for_selector("#map-select option[value='labelled-house']", state="attached", timeout=10_000)
        page.select_option("#map-select", "labelled-house")
        page.fill("#instruction", "Walk through the hallway into the kitchen and stop next to the fridge.")
        page.click("#submit")
        page.wait_for_selector("#m-state.succeeded", timeout=30_000)
        page.wait_for_function("window.sceneGraphProbe && window.sceneGraphProbe.rooms.length > 0", timeout=20_000)
        probe = page.evaluate("window.sceneGraphProbe")
        meta = page.text_content("#graph-meta")
        # The canvas really has ink where the first name was drawn (the probe is not just bookkeeping).
        ink = page.evaluate("""() => {
            const c = document.querySelector('#scene-graph'), r = window.sceneGraphProbe.rooms[0];
            const d = c.getContext('2d').getImageData(r.x - 20, r.y - 8, 40, 16).data;
            let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i] < 80 && d[i + 1] > 70 && d[i + 2] < 80) n++;
            return n; }""")
        page.locator("#scene-graph").scroll_into_view_if_needed()
        shot = page.screenshot(full_page=True)
        card = page.locator("#scene-graph").screenshot()
    out = REPO / "runs" / "screenshots"
    out.mkdir(parents=True, exist_ok=True)
    (out / "dashboard_scene_graph.png").write_bytes(shot)
    (out / "dashboard_scene_graph_card.png").write_bytes(card)
    assert not errors, errors
    assert not refused, refused
    assert graph_reads and all(s == 200 for s in graph_reads)
    assert probe["map_id"] == "labelled-house" and probe["floor"] == 0
    # Every room of the floor is named as the planner's text form names it ("bedroom 1", "bedroom 2").
    assert sorted(r["name"] for r in probe["rooms"]) == floor0
    assert len(set(floor0)) == len(floor0) and any(n[-1].isdigit() for n in floor0)
    assert probe["objects"] == sum(1 for o in expected.objects if o.room_id in
                                   {r.room_id for r in expected.rooms if r.floor == 0})
    assert probe["openings"] > 0
    assert ink > 10
    assert f"{len(expected.rooms)} rooms" in meta
