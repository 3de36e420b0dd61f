"""Map store: versions, listing, chunks, import, validation and crash safety."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
from shared.o3d import o3d
import pytest

from services.reconstructor.core import (
    InvalidMapIdError,
    MapFormatError,
    MapNotFoundError,
    MapStore,
)
from shared.cloud import PointCloud

REPO = Path(__file__).resolve().parents[3]


def _cloud(n: int, seed: int = 0, labels: bool = True) -> PointCloud:
    rng = np.random.default_rng(seed)
    return PointCloud(
        rng.uniform(-5, 5, (n, 3)).astype(np.float32),
        rng.integers(0, 256, (n, 3), dtype=np.uint8),
        rng.integers(-1, 5, n).astype(np.int32) if labels else None,
        {0: "wall", 1: "kitchen floor"} if labels else {},
    )


def test_versions_list_and_load(tmp_path):
    store = MapStore(tmp_path)
    a, b = _cloud(100, 1), _cloud(50, 2, labels=False)
    i1 = store.save("flat", a, source="test", scale_factors=[1.5])
    i2 = store.save("flat", b)
    store.save("other", a)
    assert (i1.version, i2.version) == (1, 2)
    assert store.versions("flat") == [1, 2]
    assert [(m.map_id, m.version) for m in store.list()] == [("flat", 2), ("other", 1)]
    assert len(store.list(all_versions=True)) == 3
    assert store.load("flat").info.point_count == 50 and store.load("flat").cloud.labels is None
    old = store.load("flat", 1)
    assert np.array_equal(old.cloud.xyz, a.xyz) and np.array_equal(old.cloud.labels, a.labels)
    assert old.info.label_names == {0: "wall", 1: "kitchen floor"} and old.info.scale_factors == [1.5]
    lo, hi = a.bounds()
    assert np.allclose(old.info.bounds_min_m, lo) and np.allclose(old.info.bounds_max_m, hi)


def test_chunks_cover_the_cloud_exactly(tmp_path):
    store = MapStore(tmp_path)
    c = _cloud(1001)
    store.save("m", c)
    chunks = list(store.chunks("m", max_points=300))
    assert [ch.index for ch in chunks] == [0, 1, 2, 3] and all(ch.count == 4 for ch in chunks)
    back = PointCloud.from_chunks(reversed(chunks))
    assert np.array_equal(back.xyz, c.xyz) and np.array_equal(back.rgb, c.rgb)
    assert np.array_equal(back.labels, c.labels)
    with pytest.raises(MapNotFoundError):
        store.chunk("m", index=4, max_points=300)


def test_bad_ids_and_missing_maps(tmp_path):
    store = MapStore(tmp_path)
    for bad in ("", "a/b", "*", "../x", "a b", "x" * 65, "$m"):
        with pytest.raises(InvalidMapIdError):
            store.save(bad, _cloud(3))
    with pytest.raises(MapNotFoundError):
        store.load("nothing")
    store.save("m", _cloud(3))
    with pytest.raises(MapNotFoundError):
        store.load("m", version=7)
    with pytest.raises(MapFormatError):
        store.save("m", _cloud(0))


def test_delete_never_reuses_a_version(tmp_path):
    store = MapStore(tmp_path)
    store.save("m", _cloud(5))
    store.save("m", _cloud(6))
    store.delete("m", 2)
    assert store.versions("m") == [1]
    assert store.save("m", _cloud(7)).version == 3


def test_import_ply_bytes_and_pcd_path(tmp_path):
    store = MapStore(tmp_path / "store")
    pts = np.random.default_rng(0).uniform(0, 3, (200, 3))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.colors = o3d.utility.Vector3dVector(np.full((200, 3), 0.2))
    ply, pcdf = tmp_path / "scan.ply", tmp_path / "scan.pcd"
    o3d.io.write_point_cloud(str(ply), pcd)
    o3d.io.write_point_cloud(str(pcdf), pcd)
    info = store.import_cloud("scan", ply.read_bytes(), filename="scan.ply")
    assert info.point_count == 200 and info.source == "import:scan.ply" and not info.has_labels
    m = store.load("scan")
    assert np.allclose(m.cloud.xyz, pts, atol=1e-6) and (m.cloud.rgb == 51).all()
    assert store.import_cloud("scan", pcdf).version == 2
    with pytest.raises(MapFormatError):
        store.import_cloud("bad", b"this is not a point cloud", filename="junk.ply")
    with pytest.raises(MapFormatError):
        store.import_cloud("bad", b"x", filename="mesh.obj")
    assert store.list() == [store.info("scan")]


def test_shared_data_scannet_import(shared_data, tmp_path):
    raw = np.fromfile(shared_data / "scannet" / "scannet_scene0000_00.bin", dtype=np.float32).reshape(-1, 6)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(raw[:, :3].astype(np.float64)))
    pcd.colors = o3d.utility.Vector3dVector(raw[:, 3:].astype(np.float64) / 255.0)
    path = tmp_path / "scene0000_00.ply"
    o3d.io.write_point_cloud(str(path), pcd)
    info = MapStore(tmp_path / "store").import_cloud("scannet0", path)
    assert info.point_count == len(raw)


def test_failure_mid_write_leaves_no_version(tmp_path, monkeypatch):
    store = MapStore(tmp_path)
    store.save("m", _cloud(10))

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "rename", boom)
    with pytest.raises(OSError):
        store.save("m", _cloud(20))
    monkeypatch.undo()
    assert store.versions("m") == [1]
    assert not [p for p in (tmp_path / "m").iterdir() if p.name.startswith(".tmp")]
    assert store.load("m").info.point_count == 10


def test_corrupted_cloud_is_detected(tmp_path):
    store = MapStore(tmp_path, cache_maps=0)
    store.save("m", _cloud(100))
    ply = next((tmp_path / "m").glob("v*/cloud.ply"))
    data = bytearray(ply.read_bytes())
    data[-5] ^= 0xFF
    ply.write_bytes(bytes(data))
    with pytest.raises(MapFormatError):
        store.load("m")


@pytest.mark.system  # writers as their own processes, killed
def test_killed_writer_never_leaves_a_broken_map(tmp_path):
    # A writer storing big maps in a loop is SIGKILLed at arbitrary moments; every version that is
    # visible afterwards must load and match its checksum.
    script = textwrap.dedent(f"""
        import sys, numpy as np
        sys.path.insert(0, {str(REPO)!r})
        from services.reconstructor.core import MapStore
        from shared.cloud import PointCloud
        store = MapStore({str(tmp_path)!r})
        rng = np.random.default_rng(0)
        n = 300_000
        c = PointCloud(rng.uniform(-5, 5, (n, 3)), rng.integers(0, 256, (n, 3), dtype=np.uint8),
                       rng.integers(0, 9, n).astype(np.int32))
        print("ready", flush=True)
        while True:
            store.save("m", c)
    """)
    rng = np.random.default_rng(1)
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
        try:
            assert proc.stdout.readline().strip() == b"ready"
            time.sleep(float(rng.uniform(0.3, 1.2)))
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)
    store = MapStore(tmp_path, cache_maps=0)
    versions = store.versions("m")
    for v in versions:
        m = store.load("m", v)  # checks the SHA-256 and the point count
        assert len(m.cloud) == 300_000
    # Killed mid-write at least once in three tries is near certain: the leftovers are ignored.
    assert [i.version for i in store.list(all_versions=True)] == versions


@pytest.mark.parametrize("ascii_ply", [False, True])
def test_truncated_or_garbage_clouds_raise_map_format_error(tmp_path, ascii_ply):
    store = MapStore(tmp_path / "store")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).uniform(0, 3, (300, 3))))
    path = tmp_path / "scan.ply"
    o3d.io.write_point_cloud(str(path), pcd, write_ascii=ascii_ply)
    data = path.read_bytes()
    ours = _cloud(300).save(tmp_path / "ours.ply") or (tmp_path / "ours.ply").read_bytes()
    for blob in (data[: len(data) // 2], data[: data.find(b"end_header") + 11], ours[:-9], data[:30]):
        with pytest.raises(MapFormatError):
            store.import_cloud("bad", blob, filename="scan.ply")
    # Values that only overflow as float32 are garbage too, reported as a map error (not the
    # renderer's CloudFormatError).
    huge = np.full((10, 3), 1e300)
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(huge)))
    with pytest.raises(MapFormatError):
        store.import_cloud("bad", path)
    assert store.list() == []
    assert store.import_cloud("good", data, filename="scan.ply").point_count == 300


def test_a_ply_of_ours_is_imported_a_slice_at_a_time(tmp_path, monkeypatch):
    """A file in our layout is copied into the store in slices (forced small here, so several run),
    non-finite points dropped, labels and their names kept: the same map as parsing it whole."""
    import shared.cloud as cloud_mod
    from shared.cloud import encode

    monkeypatch.setattr(cloud_mod, "_SLICE_POINTS", 7)
    c = _cloud(100, 3)
    c.xyz[[5, 50, 99]] = np.nan
    src = tmp_path / "up.part.ply"
    src.write_bytes(encode(c))
    store = MapStore(tmp_path / "maps")
    info = store.import_cloud("streamed", src, filename="room.ply")
    keep = np.isfinite(c.xyz).all(axis=1)
    assert info.point_count == 97 and info.has_labels and info.label_names == c.label_names
    assert np.allclose(info.bounds_min_m, c.xyz[keep].min(axis=0))
    assert np.allclose(info.bounds_max_m, c.xyz[keep].max(axis=0))
    got = store.load("streamed").cloud
    assert np.array_equal(got.xyz, c.xyz[keep]) and np.array_equal(got.labels, c.labels[keep])
    assert info.source == "import:room.ply"


def test_a_cut_short_ply_of_ours_leaves_no_map(tmp_path):
    from shared.cloud import encode

    src = tmp_path / "up.part.ply"
    src.write_bytes(encode(_cloud(100, 4))[:-40])
    store = MapStore(tmp_path / "maps")
    with pytest.raises(MapFormatError, match="room.ply"):
        store.import_cloud("cut", src, filename="room.ply")
    assert list((tmp_path / "maps").iterdir()) == []
