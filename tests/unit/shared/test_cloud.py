"""shared.cloud: the one PLY layout (labels inside the file), foreign files through open3d, typed errors."""

import numpy as np
import pytest

from services.reconstructor.core import MapStore
from shared.cloud import (
    CloudError,
    CloudFormatError,
    EmptyCloudError,
    PointCloud,
    decode,
    encode,
    read_cloud,
    read_cloud_bytes,
)


def cloud(n=500, seed=0, names=None):
    rng = np.random.default_rng(seed)
    return PointCloud(rng.random((n, 3), dtype=np.float32) * 5, rng.integers(0, 255, (n, 3), dtype=np.uint8),
                      rng.integers(-1, 7, n).astype(np.int32), dict(names or {}))


def same(a: PointCloud, b: PointCloud) -> bool:
    la = None if a.labels is None else a.labels.tolist()
    lb = None if b.labels is None else b.labels.tolist()
    return np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb) and la == lb


def test_round_trip_with_labels_and_names():
    c = cloud(names={1: "sofa", 2: "kitchen floor"})
    back = decode(encode(c, comment="test"))
    assert same(back, c) and back.label_names == {1: "sofa", 2: "kitchen floor"}
    plain = decode(encode(c, with_labels=False))
    assert plain.labels is None and plain.label_names == {} and np.array_equal(plain.xyz, c.xyz)


def test_save_load_keeps_labels_in_one_file(tmp_path):
    c = cloud(names={3: "bed"})
    c.save(tmp_path / "m.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]  # no side file
    back = PointCloud.load(tmp_path / "m.ply")
    assert same(back, c) and back.label_names == {3: "bed"}


def test_other_layouts_go_through_open3d(tmp_path):
    from shared.o3d import o3d

    assert decode(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n") is None
    pts = np.random.default_rng(1).random((50, 3))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    for name, ascii_ in (("a.ply", True), ("b.pcd", False)):
        assert o3d.io.write_point_cloud(str(tmp_path / name), pcd, write_ascii=ascii_)
        back = read_cloud(tmp_path / name)
        assert len(back) == 50 and back.labels is None
        np.testing.assert_allclose(back.xyz, pts, atol=1e-6)
    assert len(read_cloud_bytes((tmp_path / "b.pcd").read_bytes(), "up.pcd")) == 50


def test_truncated_missing_and_wrong_files_are_typed_errors(tmp_path):
    data = encode(cloud())
    with pytest.raises(CloudFormatError, match="vertices need"):
        decode(data[:-10])
    with pytest.raises(CloudFormatError, match="up.ply"):
        read_cloud_bytes(data[:-10], "up.ply")
    with pytest.raises(CloudFormatError, match="no such cloud file"):
        read_cloud(tmp_path / "nope.ply")
    with pytest.raises(CloudFormatError, match="only .ply and .pcd"):
        read_cloud_bytes(data, "x.txt")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\nproperty float x\n")
    with pytest.raises(CloudFormatError, match="bad.ply"):
        read_cloud(tmp_path / "bad.ply")


def test_non_finite_points_are_dropped_and_all_non_finite_is_an_error():
    c = cloud(10)
    xyz = c.xyz.copy()
    data = bytearray(encode(c))
    # Poison the first record's x in place: our layout, so decode sees it.
    body = data.index(b"end_header\n") + len(b"end_header\n")
    data[body:body + 4] = np.float32(np.nan).tobytes()
    back = decode(bytes(data))
    assert len(back) == 9 and np.array_equal(back.xyz, xyz[1:])
    allbad = PointCloud(np.zeros((3, 3), np.float32), np.zeros((3, 3), np.uint8))
    raw = bytearray(encode(allbad))
    b0 = raw.index(b"end_header\n") + len(b"end_header\n")
    for i in range(3):
        raw[b0 + i * 15:b0 + i * 15 + 4] = np.float32(np.inf).tobytes()
    with pytest.raises(CloudFormatError, match="non-finite"):
        decode(bytes(raw))


def test_errors_share_one_base_and_are_bad_input():
    for exc in (CloudFormatError, EmptyCloudError):
        assert issubclass(exc, CloudError) and issubclass(exc, ValueError)
    with pytest.raises(CloudFormatError):
        PointCloud(np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(EmptyCloudError):
        PointCloud.concatenate([])


def test_map_store_import_keeps_labels(tmp_path):
    c = cloud(names={3: "bed"})
    store = MapStore(tmp_path)
    info = store.import_cloud("curated", encode(c), filename="c.ply")
    assert info.has_labels and info.label_names == {3: "bed"}
    loaded = store.load("curated").cloud
    assert np.array_equal(np.sort(loaded.labels), np.sort(c.labels))


def test_stratified_mesh_samples_leave_no_gap_that_random_ones_leave():
    # A 1 m square wall of two triangles, 1000 samples: random samples clump and leave holes; the
    # stratified ones keep every probe of the wall within ~1.4 mean spacings of a sample.
    from scipy.spatial import cKDTree

    from shared.cloud import sample_mesh

    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    t = np.array([[0, 1, 2], [0, 2, 3]])
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 300), np.linspace(0, 1, 300)), -1).reshape(-1, 2)
    probes = np.c_[grid, np.zeros(len(grid))]
    gaps = {}
    for stratified in (False, True):
        largest = []
        for seed in range(3):
            pc = sample_mesh(v, t, np.full((4, 3), 0.5), n_points=1000, seed=seed, stratified=stratified)
            assert len(pc) == 1000 and np.abs(pc.xyz[:, 2]).max() == 0.0
            assert 0.0 <= pc.xyz[:, :2].min() and pc.xyz[:, :2].max() <= 1.0
            largest.append(cKDTree(pc.xyz).query(probes)[0].max())
        gaps[stratified] = max(largest)
    spacing = 1.0 / np.sqrt(1000)  # 3.2 cm
    assert gaps[True] < 1.4 * spacing < gaps[False]
    # Area-uniform still: each triangle of a 3:1 split mesh gets its share, to the sample.
    v2 = np.array([[0, 0, 0], [3, 0, 0], [3, 1, 0], [0, 1, 0], [4, 0, 0], [4, 1, 0]], float)
    t2 = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    pc = sample_mesh(v2, t2, np.full((6, 3), 0.5), n_points=800, stratified=True)
    assert (pc.xyz[:, 0] < 3).sum() == 600
