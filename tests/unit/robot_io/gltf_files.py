"""Writers for small scene files in published formats (glTF 2.0 binary, binary PLY with face
properties), so the loaders are tested on files laid out like the real datasets."""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np


@dataclass
class Primitive:
    vertices: np.ndarray  # (N, 3) float32, the file's own frame
    triangles: np.ndarray  # (T, 3)
    base_color: tuple[float, float, float, float] | None = None
    colors: np.ndarray | None = None  # (N, 3) float in [0, 1] -> COLOR_0
    uvs: np.ndarray | None = None  # (N, 2) glTF UVs (origin top-left) -> TEXCOORD_0
    texture: np.ndarray | None = None  # (H, W, 3) uint8 RGB -> baseColorTexture (PNG)


def write_glb(path: Path, primitives: list[Primitive]) -> Path:
    """A glTF 2.0 binary file: one mesh, one node, one material per primitive."""
    blob = bytearray()
    views, accessors, materials, images, textures, prims = [], [], [], [], [], []

    def add_view(data: bytes, target: int | None = None) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), **({"target": target} if target else {})})
        blob.extend(data)
        return len(views) - 1

    def add_accessor(arr: np.ndarray, ctype: int, kind: str, target: int, minmax: bool = False) -> int:
        view = add_view(arr.tobytes(), target)
        acc = {"bufferView": view, "componentType": ctype, "count": int(arr.shape[0]), "type": kind}
        if minmax:
            acc["min"] = arr.min(axis=0).tolist()
            acc["max"] = arr.max(axis=0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    for p in primitives:
        attrs = {"POSITION": add_accessor(np.asarray(p.vertices, np.float32), 5126, "VEC3", 34962, minmax=True)}
        if p.colors is not None:
            attrs["COLOR_0"] = add_accessor(np.asarray(p.colors, np.float32), 5126, "VEC3", 34962)
        if p.uvs is not None:
            attrs["TEXCOORD_0"] = add_accessor(np.asarray(p.uvs, np.float32), 5126, "VEC2", 34962)
        idx = add_accessor(np.asarray(p.triangles, np.uint32).reshape(-1), 5125, "SCALAR", 34963)
        pbr: dict = {"metallicFactor": 0.0}
        if p.base_color is not None:
            pbr["baseColorFactor"] = list(p.base_color)
        if p.texture is not None:
            ok, png = cv2.imencode(".png", np.ascontiguousarray(p.texture[..., ::-1]))
            assert ok
            images.append({"bufferView": add_view(png.tobytes()), "mimeType": "image/png"})
            textures.append({"source": len(images) - 1})
            pbr["baseColorTexture"] = {"index": len(textures) - 1}
        materials.append({"name": f"m{len(materials)}", "pbrMetallicRoughness": pbr})
        prims.append({"attributes": attrs, "indices": idx, "material": len(materials) - 1})
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": prims}], "materials": materials, "accessors": accessors,
        "bufferViews": views, "buffers": [{"byteLength": len(blob)}],
    }
    if images:
        doc["images"], doc["textures"] = images, textures
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    while len(blob) % 4:
        blob.append(0)
    out = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + 8 + len(blob))
    out += struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(out)
    return path


def write_ply_with_face_ids(path: Path, vertices: np.ndarray, triangles: np.ndarray, **face_props: np.ndarray) -> Path:
    """A binary little-endian PLY whose faces carry int properties (``object_id=...``)."""
    names = list(face_props)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}",
              "property float x", "property float y", "property float z", f"element face {len(triangles)}",
              "property list uchar int vertex_indices", *[f"property int {n}" for n in names], "end_header"]
    face_dt = np.dtype([("n", "u1"), ("v", "<i4", (3,))] + [(n, "<i4") for n in names])
    faces = np.zeros(len(triangles), face_dt)
    faces["n"] = 3
    faces["v"] = triangles
    for n in names:
        faces[n] = face_props[n]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(("\n".join(header) + "\n").encode() + np.asarray(vertices, "<f4").tobytes() + faces.tobytes())
    return path


def box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box: 8 vertices, 12 triangles wound outwards."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    t = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, t
