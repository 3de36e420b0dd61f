"""Foreign cloud layouts (other PLY property orders and types, ASCII PLY, extra properties, PCD) are
imported a chunk at a time (issue 31, item 4) and give the cloud the whole-file parser gives."""

from __future__ import annotations

import numpy as np
import pytest

from services.reconstructor.core import MapFormatError, MapStore
from services.reconstructor.core import foreign
from shared.cloud import read_cloud

_NP = {"float": "f4", "double": "f8", "uchar": "u1", "ushort": "u2", "int": "i4", "short": "i2", "char": "i1"}


def _rows(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-20, 20, (n, 3)).round(3)
    rgb = rng.integers(0, 256, (n, 3))
    return xyz, rgb


def write_ply(path, fmt, props, columns, pre=(), post=()):
    """``props``: [(ply type, name)]; ``columns``: name -> values; ``pre``/``post``: (name, props, rows)
    elements before / after the vertices."""
    n = len(next(iter(columns.values())))
    order = "<" if fmt == "binary_little_endian" else ">"
    head = ["ply", f"format {fmt} 1.0", "comment made by a test"]
    for name, eprops, rows in pre:
        head += [f"element {name} {len(rows)}"] + [f"property {t} {p}" for t, p in eprops]
    head += [f"element vertex {n}"] + [f"property {t} {p}" for t, p in props]
    for name, eprops, rows in post:
        head += [f"element {name} {len(rows)}"] + [f"property {t} {p}" for t, p in eprops]
    head.append("end_header")

    def body(eprops, cols, count):
        if fmt == "ascii":
            return "".join(" ".join(repr(float(cols[p][i])) if t in ("float", "double") else str(int(cols[p][i]))
                                    for t, p in eprops) + "\n" for i in range(count)).encode()
        rec = np.empty(count, np.dtype([(p, order + _NP[t]) for t, p in eprops]))
        for t, p in eprops:
            rec[p] = cols[p]
        return rec.tobytes()

    data = ("\n".join(head) + "\n").encode()
    for _, eprops, rows in pre:
        data += body(eprops, {p: [r[i] for r in rows] for i, (_, p) in enumerate(eprops)}, len(rows))
    data += body(props, columns, n)
    for _, eprops, rows in post:
        data += body(eprops, {p: [r[i] for r in rows] for i, (_, p) in enumerate(eprops)}, len(rows))
    path.write_bytes(data)
    return path


def write_pcd(path, kind, xyz, rgb=None, extra=False):
    n = len(xyz)
    fields, sizes, types = ["x", "y", "z"], [4, 4, 4], ["F", "F", "F"]
    if extra:
        fields, sizes, types = fields + ["intensity"], sizes + [4], types + ["F"]
    if rgb is not None:
        fields, sizes, types = fields + ["rgb"], sizes + [4], types + ["F"]
    head = ["# .PCD v0.7", "VERSION 0.7", "FIELDS " + " ".join(fields), "SIZE " + " ".join(map(str, sizes)),
            "TYPE " + " ".join(types), "COUNT " + " ".join("1" * len(fields)), f"WIDTH {n}", "HEIGHT 1",
            "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", f"DATA {kind}"]
    rec = np.empty(n, np.dtype([(f, "<f4") for f in fields]))
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if extra:
        rec["intensity"] = np.arange(n)
    if rgb is not None:
        packed = ((rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2].astype(np.uint32))
        rec["rgb"] = packed.view(np.float32)
    data = ("\n".join(head) + "\n").encode()
    if kind == "binary":
        data += rec.tobytes()
    else:
        data += "".join(" ".join(repr(float(v)) if f != "rgb" else np.format_float_scientific(v, unique=True)
                                 for f, v in zip(fields, r)) + "\n" for r in rec.tolist()).encode()
    path.write_bytes(data)
    return path


XYZ = [("float", "x"), ("float", "y"), ("float", "z")]
RGB = [("uchar", "red"), ("uchar", "green"), ("uchar", "blue")]


def _cols(xyz, rgb, **extra):
    return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0], "green": rgb[:, 1],
            "blue": rgb[:, 2], **extra}


CASES = {
    "float xyz, uchar rgb, big endian": lambda p, xyz, rgb: write_ply(p, "binary_big_endian", XYZ + RGB, _cols(xyz, rgb)),
    "double xyz, extra properties": lambda p, xyz, rgb: write_ply(
        p, "binary_little_endian", [("double", "x"), ("double", "y"), ("double", "z"), ("float", "nx"),
                                    ("float", "ny"), ("float", "nz"), *RGB, ("uchar", "alpha"), ("float", "quality")],
        _cols(xyz, rgb, nx=xyz[:, 0], ny=xyz[:, 1], nz=xyz[:, 2], alpha=rgb[:, 0], quality=xyz[:, 2])),
    "int xyz": lambda p, xyz, rgb: write_ply(p, "binary_little_endian", [("int", n) for _, n in XYZ] + RGB,
                                             _cols(np.rint(xyz), rgb)),
    "no colour": lambda p, xyz, rgb: write_ply(p, "binary_little_endian", XYZ, _cols(xyz, rgb)),
    "ascii": lambda p, xyz, rgb: write_ply(p, "ascii", XYZ + RGB, _cols(xyz, rgb)),
    "ascii, an element before and after": lambda p, xyz, rgb: write_ply(
        p, "ascii", XYZ + RGB, _cols(xyz, rgb), pre=[("camera", [("float", "f")], [(1.5,), (2.5,)])],
        post=[("edge", [("int", "a"), ("int", "b")], [(0, 1)])]),
    "binary, an element before": lambda p, xyz, rgb: write_ply(
        p, "binary_little_endian", XYZ + RGB, _cols(xyz, rgb), pre=[("camera", [("double", "f"), ("uchar", "k")],
                                                                         [(1.5, 3), (2.5, 4)])]),
    "pcd binary": lambda p, xyz, rgb: write_pcd(p, "binary", xyz, rgb, extra=True),
    "pcd ascii": lambda p, xyz, rgb: write_pcd(p, "ascii", xyz, rgb),
    "pcd binary, no colour": lambda p, xyz, rgb: write_pcd(p, "binary", xyz),
}


@pytest.mark.parametrize("case", list(CASES))
def test_foreign_layouts_import_as_the_whole_file_parser_reads_them(case, tmp_path, monkeypatch):
    # Chunks of 7 records (ASCII: of ~100 bytes) so that 50 points cross several chunk borders.
    monkeypatch.setattr(foreign, "_CHUNK_POINTS", 7)
    monkeypatch.setattr(foreign, "_CHUNK_TEXT_BYTES", 100)
    xyz, rgb = _rows(50)
    # A non-finite point is dropped by both (in binary files: "inf" is no PLY number, and open3d's ASCII
    # reader stops at it).
    binary = "ascii" not in case and case != "int xyz"
    if binary:
        xyz[3] = [np.inf, 0.0, 1.0]
    suffix = ".pcd" if case.startswith("pcd") else ".ply"
    src = CASES[case](tmp_path / f"in{suffix}", xyz, rgb)
    whole = read_cloud(src)
    store = MapStore(tmp_path / "maps", fsync=False)
    info = store.import_cloud("m", src, filename=f"upload{suffix}")
    got = store.load("m").cloud
    assert info.point_count == len(whole) == 50 - binary
    np.testing.assert_array_equal(got.xyz, whole.xyz)
    np.testing.assert_array_equal(got.rgb, whole.rgb)
    assert got.labels is None
    np.testing.assert_allclose(info.bounds_min_m, whole.xyz.min(axis=0))
    np.testing.assert_allclose(info.bounds_max_m, whole.xyz.max(axis=0))


def test_another_property_order_is_read_right(tmp_path):
    """A vertex layout open3d misreads (it gives garbage and warns): the chunked reader follows the header."""
    xyz, rgb = _rows(20)
    props = [("uchar", "red"), ("float", "z"), ("float", "nx"), ("float", "x"), ("uchar", "blue"), ("float", "y"),
             ("uchar", "green")]
    src = write_ply(tmp_path / "in.ply", "binary_little_endian", props, _cols(xyz, rgb, nx=xyz[:, 0]))
    store = MapStore(tmp_path / "maps", fsync=False)
    store.import_cloud("m", src, filename="x.ply")
    got = store.load("m").cloud
    np.testing.assert_allclose(got.xyz, xyz.astype(np.float32))
    np.testing.assert_array_equal(got.rgb, rgb.astype(np.uint8))


@pytest.mark.parametrize("fmt", ["binary_big_endian", "ascii"])
def test_float_colours_in_0_1_are_scaled(tmp_path, fmt):
    """open3d divides every colour by 255 (float colours in [0, 1] come out black): the chunked reader
    scales float channels to 0-255."""
    xyz, rgb = _rows(10)
    props = XYZ + [("float", "red"), ("float", "green"), ("float", "blue")]
    src = write_ply(tmp_path / "in.ply", fmt, props, _cols(xyz, rgb / 255.0))
    store = MapStore(tmp_path / "maps", fsync=False)
    store.import_cloud("m", src, filename="x.ply")
    np.testing.assert_array_equal(store.load("m").cloud.rgb, rgb.astype(np.uint8))


def _truncate(p):
    p.write_bytes(p.read_bytes()[:-40])


def _garble_ascii(p):
    lines = p.read_bytes().split(b"\n")
    lines[-10] = b"1.0 abc 2.0 3 4 5"
    p.write_bytes(b"\n".join(lines))


def _bad_header(p):
    p.write_bytes(p.read_bytes().replace(b"element vertex", b"element vertex x", 1).replace(b"POINTS", b"POINTS x", 1))


BROKEN = {
    "truncated binary ply": ("binary, an element before", _truncate),
    "truncated ascii ply": ("ascii", lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])),
    "garbled ascii ply": ("ascii", _garble_ascii),
    "malformed ply header": ("ascii", _bad_header),
    "truncated binary pcd": ("pcd binary", _truncate),
    "garbled ascii pcd": ("pcd ascii", _garble_ascii),
    "malformed pcd header": ("pcd binary", _bad_header),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_files_give_a_typed_error_and_store_nothing(case, tmp_path, monkeypatch):
    monkeypatch.setattr(foreign, "_CHUNK_POINTS", 7)
    monkeypatch.setattr(foreign, "_CHUNK_TEXT_BYTES", 100)
    make, breaks = BROKEN[case]
    suffix = ".pcd" if make.startswith("pcd") else ".ply"
    src = CASES[make](tmp_path / f"in{suffix}", *_rows(50))
    breaks(src)
    store = MapStore(tmp_path / "maps", fsync=False)
    with pytest.raises(MapFormatError, match="upload"):
        store.import_cloud("m", src, filename=f"upload{suffix}")
    assert store.list() == []
    assert not (tmp_path / "maps" / "m").exists()


def test_a_file_that_must_be_parsed_whole_is_bounded(tmp_path):
    """A compressed PCD is one LZF block: parsed whole, so only up to the store's size limit."""
    src = tmp_path / "c.pcd"
    src.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\nHEIGHT 1\n"
                    b"POINTS 10\nDATA binary_compressed\n" + bytes(200))
    store = MapStore(tmp_path / "maps", fsync=False, max_whole_bytes=100)
    with pytest.raises(MapFormatError, match="parsed whole"):
        store.import_cloud("m", src, filename="c.pcd")
    assert store.list() == []
