"""The download routes on a gateway over a FakeBus with the scripted planner and reconstructor:
a mission's .rrd read back with rerun's own reader, its trajectory CSV, a map as PCD and Nav2."""

from __future__ import annotations

import csv
import io
import zipfile
from contextlib import contextmanager

import numpy as np
from shared.o3d import o3d
import pytest
import rerun as rr
import yaml
from fastapi.testclient import TestClient

from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from tests.doubles.scripted_services import ScriptedMapper, ScriptedPlanner, ScriptedReconstructor
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import TypedBus
from tests.unit.export.test_nav2 import read_pgm, room_cloud
from tests.waiting import wait_until

STEPS = 4  # the scripted planner's steps; the last one stops


@pytest.fixture
def net():
    net = FakeNetwork()
    bus = FakeBus(net)
    typed = TypedBus(bus, "scripted")
    recon = ScriptedReconstructor(typed)
    xyz = room_cloud()
    recon.add("house", xyz, np.full((len(xyz), 3), 180), labels=np.zeros(len(xyz), np.int32))
    planner = ScriptedPlanner(typed, steps=STEPS, step_interval_s=0.01, candidates=3, image_px=32)
    mapper = ScriptedMapper(typed, stages=3, reconstructor=recon)
    yield net
    mapper.close()
    planner.close()
    recon.close()
    bus.close()


@pytest.fixture
def gateway(net, tmp_path):
    @contextmanager
    def make(**overrides):
        settings = GatewaySettings(instance="gw-dl", db_path=tmp_path / "gw.sqlite3", request_timeout_s=2.0,
                                   recordings_dir=tmp_path / "rec", **overrides)
        with TestClient(create_app(settings, bus_factory=lambda _s: FakeBus(net))) as client:
            yield client, settings

    return make


def run_mission(client, **options) -> str:
    r = client.post("/missions", json={"instruction": "go to the kitchen", "map_id": "house", "options": options})
    assert r.status_code == 202, r.text
    mid = r.json()["id"]
    wait_until(lambda: client.get(f"/missions/{mid}").json()["state"] == "succeeded", timeout_s=20)
    return mid


def rrd_contents(path) -> dict[str, dict]:
    """entity -> {rows, static, columns, batches} via rerun's own RRD reader."""
    out: dict[str, dict] = {}
    for chunk in rr.chunk.RrdReader(str(path)).stream():
        e = out.setdefault(chunk.entity_path.lstrip("/"), {"rows": 0, "static": chunk.is_static, "columns": set(), "batches": []})
        e["rows"] += chunk.num_rows
        batch = chunk.to_record_batch()
        e["columns"] |= set(batch.schema.names)
        e["batches"].append(batch)
    return out


def test_recorded_mission_reads_back_with_every_entity(gateway, tmp_path):
    with gateway() as (client, settings):
        mid = run_mission(client, record=True, goal_m=[3.0, 2.0, 0.3], reference_path_m=[[0, 0, 0.3], [3, 2, 0.3]])
        # The writer records it when it ends, without anybody asking.
        path = settings.recordings_dir / f"{mid}.rrd"
        wait_until(path.is_file, timeout_s=30)
        r = client.get(f"/missions/{mid}/recording.rrd")
        assert r.status_code == 200 and r.content == path.read_bytes()
    got = tmp_path / "got.rrd"
    got.write_bytes(r.content)
    (entry,) = rr.chunk.RrdReader(str(got)).recordings()
    assert entry.application_id == "spatialant" and entry.recording_id == mid
    c = rrd_contents(got)
    # one row per step for everything a step carries
    for entity in ["decisions", "world/candidates", "world/chosen", "views/panorama", "views/spatial_map",
                   "views/candidates/0/observed", "views/candidates/2/anticipated", "world/agent/heading",
                   "timings/observe", "timings/policy"]:
        assert c[entity]["rows"] == STEPS, (entity, c[entity]["rows"])
    assert c["world/agent"]["rows"] == STEPS + 1  # and once more at the end
    assert c["events"]["rows"] == 2  # started, finished
    assert c["metrics/ne_m"]["rows"] == 1
    # static: the map cloud with all its points, the goal, the reference path
    cloud = c["world/map"]
    assert cloud["static"] and cloud["rows"] == 1
    positions = cloud["batches"][0].column("Points3D:positions")
    assert len(positions[0]) == len(room_cloud())
    assert c["world/goal"]["static"] and c["world/reference"]["static"]
    # the decisions carry the reasoning text; candidates carry 4 points (3 waypoints + stop)
    texts = [t.as_py() for b in c["decisions"]["batches"] for t in b.column("TextLog:text")]
    assert any("anticipated view shows a doorway" in str(t) for t in texts)
    cands = c["world/candidates"]["batches"][0].column("Points3D:positions")
    assert len(cands[0]) == 4
    assert "step" in c["decisions"]["columns"] and "time" in c["decisions"]["columns"]


def test_recording_follows_the_option_then_the_setting(gateway):
    with gateway() as (client, _):
        plain = run_mission(client)
        r = client.get(f"/missions/{plain}/recording.rrd")
        assert r.status_code == 404 and "not recorded" in r.json()["detail"]
        assert client.get("/missions/m-nope/recording.rrd").status_code == 404
    with gateway(record_jobs=True) as (client, settings):
        on = run_mission(client)
        off = run_mission(client, record=False)
        assert client.get(f"/missions/{on}/recording.rrd").status_code == 200
        assert client.get(f"/missions/{off}/recording.rrd").status_code == 404
        assert not (settings.recordings_dir / f"{off}.rrd").exists()


def test_a_missing_recording_is_written_on_first_download(gateway):
    with gateway(record_jobs=True) as (client, settings):
        mid = run_mission(client)
        path = settings.recordings_dir / f"{mid}.rrd"
        wait_until(path.is_file, timeout_s=30)
        path.unlink()  # as if the gateway had been down when the mission ended
        r = client.get(f"/missions/{mid}/recording.rrd")
        assert r.status_code == 200 and path.is_file()


def test_trajectory_csv(gateway):
    with gateway() as (client, _):
        mid = run_mission(client)
        r = client.get(f"/missions/{mid}/trajectory.csv")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(r.text)))
    # the start, then one row per step (the scripted planner reports the pose after each move)
    assert len(rows) == STEPS + 1 and [row["action"] for row in rows][-1] == "stop"
    assert [int(row["step"]) for row in rows] == list(range(STEPS + 1)) and rows[0]["x_m"] == "0.0000"
    assert float(rows[-1]["distance_m"]) == pytest.approx(1.5 * (STEPS - 1), abs=1e-3)


def test_map_as_pcd_and_nav2(gateway, tmp_path):
    with gateway(map_chunk_points=20_000) as (client, _):  # several chunks
        pcd = client.get("/maps/house/cloud.pcd")
        z = client.get("/maps/house/nav2.zip", params={"cell_m": 0.1})
        y = client.get("/maps/house/nav2.yaml", params={"cell_m": 0.1})
        g = client.get("/maps/house/nav2.pgm", params={"cell_m": 0.1})
        assert client.get("/maps/nope/nav2.zip").status_code == 404
        assert client.get("/maps/house/nav2.yaml", params={"cell_m": 0}).status_code == 422
    assert pcd.status_code == 200 and int(pcd.headers["content-length"]) == len(pcd.content)
    (tmp_path / "m.pcd").write_bytes(pcd.content)
    assert len(o3d.io.read_point_cloud(str(tmp_path / "m.pcd")).points) == len(room_cloud())
    assert z.status_code == 200
    files = zipfile.ZipFile(io.BytesIO(z.content))
    assert sorted(files.namelist()) == ["house-v1.pgm", "house-v1.yaml"]
    meta = yaml.safe_load(files.read("house-v1.yaml"))
    assert meta["image"] == "house-v1.pgm" and meta["resolution"] == pytest.approx(0.1)
    assert yaml.safe_load(y.content) == meta and 'filename="house-v1.pgm"' in g.headers["content-disposition"]
    img = read_pgm(files.read("house-v1.pgm"))
    assert img.shape == (round((3 + 1.0) / 0.1), round((4 + 1.0) / 0.1))  # the room plus a 0.5 m margin
    assert set(np.unique(img)) == {0, 205, 254}


def test_download_list_says_what_is_available(gateway):
    with gateway() as (client, _):
        plain = run_mission(client)
        rec = run_mission(client, record=True)
        items = {d["url"].rsplit("/", 1)[1]: d for d in client.get(f"/missions/{plain}/downloads").json()["items"]}
        assert items["trajectory.csv"]["available"] and not items["recording.rrd"]["available"]
        assert "not recorded" in items["recording.rrd"]["reason"]
        items = {d["url"].rsplit("/", 1)[1]: d for d in client.get(f"/missions/{rec}/downloads").json()["items"]}
        assert items["recording.rrd"]["available"]
        assert client.get("/missions/m-none/downloads").status_code == 404


def test_recorded_exploration_holds_its_progress_and_the_map_it_built(gateway, tmp_path):
    with gateway() as (client, _):
        r = client.post("/explorations", json={"map_id": "built", "record": True})
        assert r.status_code == 202, r.text
        xid = r.json()["id"]
        wait_until(lambda: client.get(f"/explorations/{xid}").json()["state"] == "succeeded", timeout_s=20)
        got = client.get(f"/explorations/{xid}/recording.rrd")
        assert client.get(f"/explorations/{xid}/downloads").json()["items"][0]["available"]
    assert got.status_code == 200
    (tmp_path / "x.rrd").write_bytes(got.content)
    c = rrd_contents(tmp_path / "x.rrd")
    assert c["progress"]["rows"] == 3 and c["events"]["rows"] == 5 and c["views/spatial_map"]["rows"] == 3
    assert len(c["world/map"]["batches"][0].column("Points3D:positions")[0]) == 2000  # the map it built
