"""Maps (list, info, PLY download and upload) and explorations through the gateway."""

from __future__ import annotations

import numpy as np
import open3d as o3d

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
