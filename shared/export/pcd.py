"""Binary PCD (Point Cloud Library, format v0.7) of a coloured, optionally labelled cloud.

Fields ``x y z`` float32 and ``rgb`` packed as PCL does (one float32 whose bits are 0x00RRGGBB), plus
``label`` uint32 when the cloud has labels (PCL's PointXYZRGBL; unknown label -1 is written as
0xFFFFFFFF). PCL, open3d and CloudCompare read it.
"""

from __future__ import annotations

import numpy as np


def pcd_header(point_count: int, with_labels: bool) -> bytes:
    fields = ["x", "y", "z", "rgb"] + (["label"] if with_labels else [])
    size = ["4"] * len(fields)
    types = ["F", "F", "F", "F"] + (["U"] if with_labels else [])
    lines = [
        "# .PCD v0.7 - Point Cloud Data file format (SpatialAnt)",
        "VERSION 0.7",
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(size),
        "TYPE " + " ".join(types),
        "COUNT " + " ".join(["1"] * len(fields)),
        f"WIDTH {point_count}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {point_count}",
        "DATA binary",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


def pcd_records(xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None = None,
                with_labels: bool | None = None) -> bytes:
    """Packed binary records for a header of :func:`pcd_header` (chunks concatenate)."""
    with_labels = labels is not None if with_labels is None else with_labels
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")] + ([("label", "<u4")] if with_labels else []))
    out = np.empty(len(xyz), dt)
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    c = np.asarray(rgb, np.uint32)
    # Written as uint32 bits: the reader reinterprets the float field's bytes, exactly PCL's packing.
    out["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    if with_labels:
        out["label"] = (np.asarray(labels, np.int64) if labels is not None else np.full(len(xyz), -1)).astype(np.uint32)
    return out.tobytes()


def encode_pcd(xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None = None) -> bytes:
    return pcd_header(len(xyz), labels is not None) + pcd_records(xyz, rgb, labels)


def record_size(with_labels: bool) -> int:
    return 20 if with_labels else 16
