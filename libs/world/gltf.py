"""A glTF 2.0 reader (``.glb`` and ``.gltf``) for scene meshes: geometry, node transforms, materials.

Why not open3d's ``read_triangle_model``: it goes through assimp's post-processing and takes ~9 s
for a 245k-triangle textured file (a Matterport scan has millions); reading the accessors straight
into numpy takes milliseconds plus the image decoding. What is read, per the glTF 2.0 spec:

* every triangle primitive (mode 4; strips and fans are unrolled) of every node of the default
  scene, with the node's world transform (``matrix`` or T * R * S, parents first);
* ``POSITION``, optional ``COLOR_0`` (float or normalised integers; alpha dropped) and the
  ``TEXCOORD_n`` its base-colour texture names;
* ``pbrMetallicRoughness.baseColorFactor`` / ``baseColorTexture`` (or ``KHR_materials_pbrSpecularGlossiness``
  ``diffuseFactor`` / ``diffuseTexture``); PNG / JPEG images embedded, as data URIs or as files.

Compressed geometry (Draco, meshopt) and sparse accessors raise :class:`SceneFormatError`; textures
cv2 cannot decode (``KHR_texture_basisu``) fall back to the factor colour with a warning.
"""

from __future__ import annotations

import base64
import json
import logging
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import SceneFormatError

log = logging.getLogger(__name__)

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_UNSUPPORTED = ("KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_mesh_quantization")


@dataclass
class Part:
    """One primitive in the file's scene frame; ``uvs`` per vertex in open3d's convention (v up)."""

    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray | None
    uvs: np.ndarray | None
    factor: np.ndarray  # (3,) base-colour factor
    image: np.ndarray | None  # (H, W, 3) uint8 base-colour texture
    material: int  # index in the file (-1: none), so parts share one decoded image


def read_gltf(path: Path) -> tuple[list[Part], int]:
    """The file's primitives and its material count."""
    doc, bin_chunk = _load(path)
    used = set(doc.get("extensionsRequired", [])) | set(doc.get("extensionsUsed", []))
    bad = [e for e in _UNSUPPORTED if e in used]
    if bad:
        raise SceneFormatError(f"{path}: compressed glTF ({', '.join(bad)}); decompress it first (e.g. gltf-transform copy)")
    buffers = [_buffer(path, b, bin_chunk if i == 0 else None) for i, b in enumerate(doc.get("buffers", []))]
    reader = _Accessors(doc, buffers, path)
    images: dict[int, np.ndarray | None] = {}
    parts: list[Part] = []
    for mesh_index, world in _mesh_instances(doc):
        for prim in doc["meshes"][mesh_index].get("primitives", []):
            part = _primitive(doc, reader, prim, world, images, path)
            if part is not None:
                parts.append(part)
    return parts, len(doc.get("materials", []))


def _load(path: Path) -> tuple[dict, bytes | None]:
    data = path.read_bytes()
    if data[:4] == b"glTF":
        view = memoryview(data)  # chunks and buffer views without copies
        if len(data) < 20:
            raise SceneFormatError(f"{path}: truncated GLB header")
        _, version, length = struct.unpack_from("<III", data, 0)
        if version != 2:
            raise SceneFormatError(f"{path}: GLB version {version}, only 2 is supported")
        pos, doc, bin_chunk = 12, None, None
        while pos + 8 <= min(length, len(data)):
            clen, ctype = struct.unpack_from("<II", data, pos)
            chunk = view[pos + 8 : pos + 8 + clen]
            if ctype == 0x4E4F534A:
                doc = json.loads(bytes(chunk))
            elif ctype == 0x004E4942 and bin_chunk is None:
                bin_chunk = chunk
            pos += 8 + clen
        if doc is None:
            raise SceneFormatError(f"{path}: GLB without a JSON chunk")
        return doc, bin_chunk
    try:
        return json.loads(data), None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneFormatError(f"{path}: neither GLB nor glTF JSON ({exc})") from None


def _uri_bytes(path: Path, uri: str) -> bytes:
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    from urllib.parse import unquote

    f = path.parent / unquote(uri)
    if not f.is_file():
        raise SceneFormatError(f"{path}: referenced file {f} is missing")
    return f.read_bytes()


def _buffer(path: Path, b: dict, bin_chunk) -> memoryview:
    if "uri" in b:
        return memoryview(_uri_bytes(path, b["uri"]))
    if bin_chunk is None:
        raise SceneFormatError(f"{path}: a buffer without uri and no GLB binary chunk")
    return bin_chunk


class _Accessors:
    def __init__(self, doc: dict, buffers: list[memoryview], path: Path):
        self.doc, self.buffers, self.path = doc, buffers, path

    def view_bytes(self, view_index: int) -> memoryview:
        v = self.doc["bufferViews"][view_index]
        start = v.get("byteOffset", 0)
        return self.buffers[v["buffer"]][start : start + v["byteLength"]]

    def read(self, index: int, as_float: bool = False) -> np.ndarray:
        try:
            acc = self.doc["accessors"][index]
            if "sparse" in acc:
                raise SceneFormatError(f"{self.path}: sparse accessors are not supported")
            dtype = np.dtype(_COMPONENT[acc["componentType"]]).newbyteorder("<")
            width = _WIDTH[acc["type"]]
            count = int(acc["count"])
            if "bufferView" not in acc:
                out = np.zeros((count, width), dtype)
            else:
                view = self.doc["bufferViews"][acc["bufferView"]]
                buf = self.buffers[view["buffer"]]
                offset = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
                stride = view.get("byteStride") or dtype.itemsize * width
                if count == 0:
                    out = np.zeros((0, width), dtype)
                else:
                    # Interleaved or padded rows: a strided view, then one copy.
                    out = np.ndarray((count, width), dtype, buffer=buf, offset=offset, strides=(stride, dtype.itemsize)).copy()
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise SceneFormatError(f"{self.path}: bad accessor {index} ({exc})") from None
        if as_float and out.dtype.kind in "iu":
            if acc.get("normalized"):
                info = np.iinfo(out.dtype)
                out = np.maximum(out.astype(np.float32) / info.max, -1.0)
            else:
                out = out.astype(np.float32)
        return out


def _mesh_instances(doc: dict):
    """(mesh index, 4x4 world matrix) for every node with a mesh in the default scene."""
    nodes = doc.get("nodes", [])
    scenes = doc.get("scenes", [])
    if scenes:
        roots = scenes[doc.get("scene", 0)].get("nodes", [])
    else:
        children = {c for n in nodes for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    stack = [(i, np.eye(4)) for i in roots]
    seen = 0
    while stack:
        i, parent = stack.pop()
        seen += 1
        if seen > 1_000_000:
            raise SceneFormatError("glTF node graph is cyclic")
        node = nodes[i]
        world = parent @ _node_matrix(node)
        if "mesh" in node:
            yield node["mesh"], world
        stack.extend((c, world) for c in node.get("children", []))


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    m = np.eye(4)
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m[:3, :3] = r * np.asarray(node.get("scale", [1.0, 1.0, 1.0]), dtype=np.float64)[None, :]
    m[:3, 3] = node.get("translation", [0.0, 0.0, 0.0])
    return m


def _triangles(mode: int, idx: np.ndarray) -> np.ndarray | None:
    if mode == 4:
        return idx[: len(idx) // 3 * 3].reshape(-1, 3)
    if mode == 5 and len(idx) >= 3:  # strip: every other triangle flips to keep the winding
        k = np.arange(len(idx) - 2)
        t = np.stack([idx[k], idx[k + 1], idx[k + 2]], axis=1)
        t[1::2] = t[1::2][:, [1, 0, 2]]
        return t
    if mode == 6 and len(idx) >= 3:  # fan
        k = np.arange(1, len(idx) - 1)
        return np.stack([np.full(len(k), idx[0]), idx[k], idx[k + 1]], axis=1)
    return None  # points and lines: not surfaces


def _primitive(doc, reader: _Accessors, prim: dict, world: np.ndarray, images: dict, path: Path) -> Part | None:
    attrs = prim.get("attributes", {})
    if "POSITION" not in attrs:
        return None
    v = reader.read(attrs["POSITION"], as_float=True).astype(np.float64)[:, :3]
    idx = reader.read(prim["indices"]).reshape(-1).astype(np.int64) if "indices" in prim else np.arange(len(v))
    t = _triangles(int(prim.get("mode", 4)), idx)
    if t is None or len(t) == 0:
        return None
    if t.max() >= len(v) or t.min() < 0:
        raise SceneFormatError(f"{path}: triangle indices out of range")
    v = v @ world[:3, :3].T + world[:3, 3]
    if np.linalg.det(world[:3, :3]) < 0:
        t = t[:, [0, 2, 1]]  # a mirroring node transform reverses the winding (glTF spec)
    colors = None
    if "COLOR_0" in attrs:
        colors = np.clip(reader.read(attrs["COLOR_0"], as_float=True)[:, :3], 0.0, 1.0).astype(np.float32)
    mat_index = int(prim.get("material", -1))
    factor, tex_info = np.ones(3, np.float32), None
    if 0 <= mat_index < len(doc.get("materials", [])):
        mat = doc["materials"][mat_index]
        pbr = mat.get("pbrMetallicRoughness", {})
        sg = mat.get("extensions", {}).get("KHR_materials_pbrSpecularGlossiness")
        src = sg if sg is not None and "pbrMetallicRoughness" not in mat else pbr
        factor = np.asarray((src.get("diffuseFactor") if src is sg else src.get("baseColorFactor")) or [1, 1, 1, 1], np.float32)[:3]
        tex_info = src.get("diffuseTexture") if src is sg else src.get("baseColorTexture")
    image, uvs = None, None
    if tex_info is not None:
        uv_key = f"TEXCOORD_{int(tex_info.get('texCoord', 0))}"
        if uv_key in attrs:
            image = _texture_image(doc, reader, int(tex_info["index"]), images, path)
            if image is not None:
                uv = reader.read(attrs[uv_key], as_float=True)[:, :2].astype(np.float32)
                uvs = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)  # glTF's v runs down, open3d's up
    return Part(v, t.astype(np.int32), colors, uvs, np.clip(factor, 0.0, 1.0), image, mat_index)


def _texture_image(doc, reader: _Accessors, tex_index: int, cache: dict, path: Path) -> np.ndarray | None:
    if tex_index in cache:
        return cache[tex_index]
    img = None
    try:
        tex = doc["textures"][tex_index]
        source = tex.get("source")
        if source is None:
            log.warning("%s: texture %d has no decodable source (%s); using the base-colour factor",
                        path.name, tex_index, ", ".join(tex.get("extensions", {})) or "none")
        else:
            im = doc["images"][source]
            data = reader.view_bytes(im["bufferView"]) if "bufferView" in im else _uri_bytes(path, im["uri"])
            dec = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            if dec is None:
                log.warning("%s: image %d (%s) cannot be decoded; using the base-colour factor", path.name, source, im.get("mimeType", "?"))
            else:
                img = cv2.cvtColor(dec, cv2.COLOR_BGR2RGB)
    except (KeyError, IndexError, TypeError) as exc:
        raise SceneFormatError(f"{path}: bad texture {tex_index} ({exc})") from None
    cache[tex_index] = img
    return img
