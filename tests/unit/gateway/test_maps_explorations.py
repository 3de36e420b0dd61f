"""Maps (list, info, PLY download and upload) and explorations through the gateway."""

from __future__ import annotations

import numpy as np
from shared.o3d import o3d

from shared.cloud import decode
from tests.doubles.scripted_services import ply_bytes
from tests.waiting import wait_until


def test_list_and_info(world, gateway):
    with gateway() as client:
        maps = client.get("/maps").json()
        assert [m["map_id"] for m in maps] == ["house"]
        info = client.get("/maps/house").json()
        assert info["point_count"] == 5000 and info["has_labels"] is True
        r = client.get("/maps/nowhere")
        assert r.status_code == 404 and "nowhere" in r.json()["detail"]
        assert client.get("/maps/bad*id").status_code == 422


def test_cloud_ply_streams_every_chunk_and_open3d_reads_it(world, gateway, tmp_path):
    xyz = np.random.default_rng(1).uniform(-3, 3, (2500, 3)).astype(np.float32)
    rgb = np.random.default_rng(2).integers(0, 256, (2500, 3)).astype(np.uint8)
    world.reconstructor.add("room", xyz, rgb)
    with gateway(map_chunk_points=1000) as client:  # three chunks
        r = client.get("/maps/room/cloud.ply")
        assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content)
        assert 'filename="room-v1.ply"' in r.headers["content-disposition"]
        labelled = client.get("/maps/house/cloud.ply").content
        assert client.get("/maps/nowhere/cloud.ply").status_code == 404
    path = tmp_path / "room.ply"
    path.write_bytes(r.content)
    pcd = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(pcd.points), xyz, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pcd.colors) * 255, rgb, atol=0.5)
    assert b"property int label" in labelled[:400]


def test_cloud_ply_keeps_where_the_points_were_seen_from(world, gateway):
    # A built map records each point's view direction (the renderer's side test reads it): the
    # download carries it, so the file uploaded again renders as the original.
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-3, 3, (2500, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (2500, 3)).astype(np.uint8)
    views = rng.integers(-127, 128, (2500, 3)).astype(np.int8)
    world.reconstructor.add("seen", xyz, rgb, view_dirs=views)
    with gateway(map_chunk_points=1000) as client:
        r = client.get("/maps/seen/cloud.ply")
    assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content)
    cloud = decode(r.content)
    assert np.array_equal(cloud.view_dirs, views) and np.array_equal(cloud.xyz, xyz)


def test_upload_a_ply_then_use_it_for_a_mission(world, gateway):
    xyz = np.random.default_rng(3).uniform(0, 4, (800, 3))
    rgb = np.random.default_rng(4).integers(0, 256, (800, 3))
    with gateway() as client:
        r = client.post("/maps?map_id=office&filename=office.ply", content=ply_bytes(xyz, rgb),
                        headers={"Content-Type": "application/octet-stream"})
        assert r.status_code == 201, r.text
        assert r.json()["point_count"] == 800 and r.headers["location"] == "/maps/office"
        assert client.get("/maps/office").json()["source"] == "upload:office.ply"
        assert client.post("/missions", json={"instruction": "go", "map_id": "office"}).status_code == 202
        assert client.post("/maps?map_id=office", content=b"").status_code == 422
        assert client.post("/maps?map_id=office", content=b"GIF89a....").status_code == 415
        assert client.post("/maps?map_id=office&filename=x.obj", content=b"ply\n").status_code == 422
        bad = client.post("/maps?map_id=junk", content=b"ply\nformat ascii 1.0\nend_header\n")
        assert bad.status_code == 422 and "no points" in bad.json()["detail"]


def test_upload_size_limit(world, gateway):
    with gateway(max_upload_bytes=4096) as client:
        r = client.post("/maps?map_id=big", content=b"ply\n" + b"0" * 5000)
        assert r.status_code == 413


def test_exploration_reports_progress_and_builds_a_map(world, gateway):
    with gateway() as client:
        r = client.post("/explorations", json={"map_id": "new-house", "max_steps": 50})
        assert r.status_code == 202
        xid = r.json()["id"]
        rec = wait_until(lambda: (x := client.get(f"/explorations/{xid}").json())["state"] == "succeeded" and x)
        assert rec["progress"] == 1.0 and rec["map_id"] == "new-house" and rec["stage"] == "done"
        assert rec["images"]["map"].startswith(f"/explorations/{xid}/events/")
        assert client.get(rec["images"]["map"]).status_code == 200
        assert "new-house" in [m["map_id"] for m in client.get("/maps").json()]
        assert client.get("/explorations").json()["total"] == 1
        assert client.get(f"/missions/{xid}").status_code == 404  # an exploration is not a mission
        with client.stream("GET", f"/explorations/{xid}/events") as s:
            assert s.read().decode().count("\nid: ") + 0 >= 4
        assert client.post("/explorations", json={"max_steps": 0}).status_code == 422
        assert client.post("/explorations", json={"reconstruction": "a/b"}).status_code == 422


def _exploration(client, xid):
    return client.get(f"/explorations/{xid}").json()


def test_cancel_a_running_exploration(world, gateway):
    with gateway() as client:
        # A map id with "hang": the scripted mapper holds in its last stage until cancelled.
        xid = client.post("/explorations", json={"map_id": "hang-house"}).json()["id"]
        wait_until(lambda: _exploration(client, xid)["stage"] == "reconstructing", what="the reconstructing stage")
        r = client.post(f"/explorations/{xid}/cancel")
        assert r.status_code == 202, r.text
        assert r.json()["id"] == xid and r.json()["url"] == f"/explorations/{xid}"
        rec = wait_until(lambda: (x := _exploration(client, xid))["state"] == "cancelled" and x, what="cancelled")
        # The stage it was stopped in, said by the mapper's own final event.
        assert rec["stage"] == "reconstructing" and rec["message"] == "cancelled on request while reconstructing"
        assert rec["progress"] < 1.0 and world.mapper.cancels == 1
        assert "hang-house" not in [m["map_id"] for m in client.get("/maps").json()]
        again = client.post(f"/explorations/{xid}/cancel")
        assert again.status_code == 409 and "already cancelled" in again.json()["detail"]
        assert world.mapper.cancels == 1  # a refused cancel never reaches the mapper
        assert client.post("/explorations/x-unknown/cancel").status_code == 404
        assert client.post("/explorations/bad*id/cancel").status_code == 422
        assert client.post(f"/missions/{xid}/cancel").status_code == 404  # an exploration is not a mission


def test_cancelling_an_ended_exploration_is_refused_and_changes_nothing(world, gateway):
    with gateway() as client:
        xid = client.post("/explorations", json={"map_id": "done-house"}).json()["id"]
        before = wait_until(lambda: (x := _exploration(client, xid))["state"] == "succeeded" and x)
        r = client.post(f"/explorations/{xid}/cancel")
        assert r.status_code == 409 and "already ended (succeeded)" in r.json()["detail"]
        assert _exploration(client, xid) == before and world.mapper.cancels == 0


def test_an_exploration_no_mapper_runs_is_cancelled_by_the_gateway(world, gateway):
    from services.gateway.records import JobKind

    with gateway() as client:
        # A row the mapper never heard of (its mapper restarted and forgot it): it could never end.
        client.app.state.store.create_job(JobKind.EXPLORATION, "x-orphan", {"map_id": "lost"})
        r = client.post("/explorations/x-orphan/cancel")
        assert r.status_code == 202 and r.json()["state"] == "cancelled"
        rec = _exploration(client, "x-orphan")
        assert rec["state"] == "cancelled" and "no mapper runs it any more" in rec["message"]
        with client.stream("GET", "/explorations/x-orphan/events") as s:
            assert "cancelled" in s.read().decode()


def test_scene_graph_route(world, gateway):
    # A labelled floor and a wall: the real builder behind the scripted store gives one unnamed-free room.
    rng = np.random.default_rng(7)
    floor = np.c_[rng.uniform(0, 4, (3000, 2)), np.zeros(3000)]
    wall = np.c_[rng.uniform(0, 4, 600), np.zeros(600), rng.uniform(0, 2.5, 600)]
    xyz = np.r_[floor, wall]
    labels = np.r_[np.zeros(3000), np.ones(600)].astype(np.int32)
    world.reconstructor.add("flat", xyz, np.full((len(xyz), 3), 128), labels)
    with gateway() as client:
        r = client.get("/maps/flat/scene-graph.json")
        assert r.status_code == 200, r.text
        g = r.json()
        assert g["map_id"] == "flat" and g["free_space"][0]["cell_m"] == 0.25
        assert len(g["rooms"]) == 1 and g["rooms"][0]["area_m2"] > 10
        assert client.get("/maps/nowhere/scene-graph.json").status_code == 404
        assert client.get("/maps/bad*id/scene-graph.json").status_code == 422
