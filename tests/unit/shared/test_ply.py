import numpy as np
import pytest

from services.reconstructor.core import MapStore
from shared import ply


def cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.random((n, 3), dtype=np.float32) * 5, rng.integers(0, 255, (n, 3), dtype=np.uint8),
            rng.integers(-1, 7, n).astype(np.int32))


def test_round_trip_with_labels_and_names():
    xyz, rgb, labels = cloud()
    data = ply.encode(xyz, rgb, labels, {1: "sofa", 2: "kitchen floor"}, comment="test")
    x2, c2, l2, names = ply.decode(data)
    assert np.array_equal(x2, xyz) and np.array_equal(c2, rgb) and np.array_equal(l2, labels)
    assert names == {1: "sofa", 2: "kitchen floor"}
    x3, _, l3, names3 = ply.decode(ply.encode(xyz, rgb))
    assert l3 is None and names3 == {} and np.array_equal(x3, xyz)


def test_other_layouts_are_left_to_open3d_and_truncation_is_an_error():
    assert ply.decode(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n") is None
    xyz, rgb, labels = cloud()
    with pytest.raises(ValueError, match="vertices need"):
        ply.decode(ply.encode(xyz, rgb, labels)[:-10])


def test_map_store_import_keeps_labels(tmp_path):
    xyz, rgb, labels = cloud()
    store = MapStore(tmp_path)
    info = store.import_cloud("curated", ply.encode(xyz, rgb, labels, {3: "bed"}), filename="c.ply")
    assert info.has_labels and info.label_names == {3: "bed"}
    loaded = store.load("curated").cloud
    assert np.array_equal(np.sort(loaded.labels), np.sort(labels))
