"""The project's one PLY layout for coloured, optionally labelled clouds.

Binary little-endian: ``x y z`` float32, ``red green blue`` uchar and, when labelled, ``label`` int32;
label names travel in a ``comment label_names {json}`` header line. The gateway streams maps in it,
the evaluation uploads curated clouds in it, and the map store reads it back with the labels
(open3d alone would drop them). Other layouts (ASCII, doubles, PCD) are left to open3d.
"""

from __future__ import annotations

import json

import numpy as np

_BASE = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
_LABEL_COMMENT = "label_names "


def vertex_dtype(with_labels: bool) -> np.dtype:
    return np.dtype(_BASE + ([("label", "<i4")] if with_labels else []))


def header(point_count: int, with_labels: bool, label_names: dict[int, str] | None = None,
           comment: str = "") -> bytes:
    lines = ["ply", "format binary_little_endian 1.0"]
    if comment:
        lines.append(f"comment {comment}")
    if with_labels and label_names:
        names = {str(k): v for k, v in sorted(label_names.items())}
        lines.append("comment " + _LABEL_COMMENT + json.dumps(names, separators=(",", ":")))
    types = {"f4": "float", "u1": "uchar", "i4": "int"}
    dt = vertex_dtype(with_labels)
    lines += [f"element vertex {point_count}"] + [
        f"property {types[dt.fields[n][0].str[1:]]} {n}" for n in dt.names
    ] + ["end_header"]
    return ("\n".join(lines) + "\n").encode("ascii")


def records(xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None = None, with_labels: bool | None = None) -> bytes:
    """Packed vertex records (one vectorised copy); ``with_labels`` without labels writes -1."""
    with_labels = labels is not None if with_labels is None else with_labels
    out = np.empty(len(xyz), vertex_dtype(with_labels))
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    out["red"], out["green"], out["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if with_labels:
        out["label"] = labels if labels is not None else -1
    return out.tobytes()


def encode(xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None = None,
           label_names: dict[int, str] | None = None, comment: str = "") -> bytes:
    return header(len(xyz), labels is not None, label_names, comment) + records(xyz, rgb, labels)


def decode(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[int, str]] | None:
    """(xyz, rgb, labels, label_names) for a file in our layout; None for any other PLY."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        return None
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        return None
    props = [ln.split()[1:] for ln in lines if ln.startswith("property ")]
    count = next((int(ln.split()[2]) for ln in lines if ln.startswith("element vertex ")), None)
    elements = [ln for ln in lines if ln.startswith("element ")]
    with_labels = props == [list(p) for p in ([["float", "x"], ["float", "y"], ["float", "z"], ["uchar", "red"],
                                               ["uchar", "green"], ["uchar", "blue"], ["int", "label"]])]
    if count is None or len(elements) != 1 or not (with_labels or props == [
            ["float", "x"], ["float", "y"], ["float", "z"], ["uchar", "red"], ["uchar", "green"], ["uchar", "blue"]]):
        return None
    dtype = vertex_dtype(with_labels)
    body = data[end + len(b"end_header\n"):]
    if len(body) < count * dtype.itemsize:
        raise ValueError(f"PLY body holds {len(body)} bytes, {count} vertices need {count * dtype.itemsize}")
    rec = np.frombuffer(body, dtype, count)
    names: dict[int, str] = {}
    for ln in lines:
        if ln.startswith("comment " + _LABEL_COMMENT):
            names = {int(k): str(v) for k, v in json.loads(ln[len("comment " + _LABEL_COMMENT):]).items()}
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    rgb = np.stack([rec["red"], rec["green"], rec["blue"]], axis=1)
    return xyz, rgb, (np.ascontiguousarray(rec["label"]) if with_labels else None), names
