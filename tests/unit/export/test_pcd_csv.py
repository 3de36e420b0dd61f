"""PCD read back by open3d (an independent reader) and the trajectory CSV by the csv module."""

from __future__ import annotations

import csv
import io

import numpy as np
from shared.o3d import o3d

from shared.export import encode_pcd, trajectory_csv
from shared.export.pcd import pcd_header, pcd_records


def test_binary_pcd_reads_back_in_open3d(tmp_path):
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-5, 5, (1000, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (1000, 3), dtype=np.uint8)
    path = tmp_path / "c.pcd"
    path.write_bytes(encode_pcd(xyz, rgb))
    pcd = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(pcd.points), xyz, atol=1e-6)
    np.testing.assert_array_equal(np.round(np.asarray(pcd.colors) * 255).astype(np.uint8), rgb)


def test_labelled_pcd_chunks_concatenate(tmp_path):
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    rgb = np.full((10, 3), 7, np.uint8)
    labels = np.array([0, 1, 2, -1, 4, 5, 6, 7, 8, 9], np.int32)
    data = pcd_header(10, True) + pcd_records(xyz[:4], rgb[:4], labels[:4]) + pcd_records(xyz[4:], rgb[4:], labels[4:])
    head, body = data.split(b"DATA binary\n")
    assert b"FIELDS x y z rgb label" in head and b"POINTS 10" in head
    rec = np.frombuffer(body, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"), ("label", "<u4")]))
    assert len(rec) == 10
    np.testing.assert_array_equal(rec["label"].view(np.int32), labels)
    assert int(rec["rgb"][0]) == (7 << 16) | (7 << 8) | 7
    (tmp_path / "l.pcd").write_bytes(data)
    assert len(o3d.io.read_point_cloud(str(tmp_path / "l.pcd")).points) == 10


def test_trajectory_csv_columns_and_distance():
    text = trajectory_csv([{"position_m": (0, 0, 0), "heading_rad": 0.0, "action": "waypoint"},
                           {"position_m": (3, 4, 0), "step": 1, "action": "stop"}])
    rows = list(csv.DictReader(io.StringIO(text)))
    assert [r["step"] for r in rows] == ["0", "1"]
    assert float(rows[1]["distance_m"]) == 5.0 and rows[1]["heading_rad"] == "" and rows[0]["action"] == "waypoint"
