"""Semantics a dataset ships beside its scene file, as per-triangle labels, rooms and objects.

Two published layouts (the files sit beside the render mesh; all coordinates are in the render
mesh's file frame and go through the same file -> world matrix):

* **Matterport3D** (``mp3d/<scan>/<scan>.glb``): ``<scan>.house`` (Matterport's ASCII 1.1 house
  format: ``L`` levels, ``R`` regions with a one-letter label and a box, ``C`` categories with their
  mpcat40 names, ``O`` objects as oriented boxes, ``E`` segments of an object) and, when present,
  ``<scan>_semantic.ply``, whose faces carry ``object_id`` (Habitat's instance mesh) or
  ``segment_id`` / ``category_id`` (Matterport's ``house_segmentations`` mesh). Without that mesh a
  triangle takes the label of the object box that contains it.
* **HM3D-Semantics** (``hm3d/<split>/<id>-<scene>/<scene>.glb``): ``<scene>.semantic.glb`` (the same
  scan, each object painted one flat colour, in its texture or vertex colours) and
  ``<scene>.semantic.txt`` (a header line, then ``id,HEX,"category",region`` per object).

Labels are transferred from the semantic mesh to the render mesh by the nearest semantic triangle
to each render triangle's centroid. Rooms come from MP3D regions (HM3D regions are unnamed);
objects from MP3D object boxes or the extent of each HM3D object's triangles.
"""

from __future__ import annotations

import csv
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SceneFormatError
from .scene_layout import Room, SceneObject
from .scene_files import read_mesh_file, scan_name

log = logging.getLogger(__name__)

# Matterport3D region label codes (the house format's README).
MP3D_REGION_TYPES: dict[str, str] = {
    "a": "bathroom", "b": "bedroom", "c": "closet", "d": "dining room", "e": "entryway", "f": "family room",
    "g": "garage", "h": "hallway", "i": "library", "j": "laundry room", "k": "kitchen", "l": "living room",
    "m": "meeting room", "n": "lounge", "o": "office", "p": "porch", "r": "game room", "s": "staircase",
    "t": "toilet", "u": "utility room", "v": "tv room", "w": "gym", "x": "outdoor", "y": "balcony",
    "z": "other room", "B": "bar", "C": "classroom", "D": "dining booth", "S": "spa", "Z": "junk", "-": "room",
}
# Surfaces every scan is made of: labels for the pixels, but no landmark to walk past.
STRUCTURE = frozenset({"wall", "floor", "ceiling", "void", "unlabeled", "unknown", "misc", "objects", "door frame", "window frame"})


@dataclass
class SceneSemantics:
    triangle_labels: np.ndarray  # (T,) int32 into label_names, -1 unknown
    label_names: dict[int, str]
    rooms: list[Room] = field(default_factory=list)
    objects: list[SceneObject] = field(default_factory=list)
    floors: int = 1
    source: str = ""


def load_semantics(path: Path, to_world: np.ndarray, vertices_w: np.ndarray, triangles: np.ndarray) -> SceneSemantics | None:
    """The semantics shipped beside ``path``, or None when there are none."""
    scan = scan_name(path)
    house = path.with_name(scan + ".house")
    if house.is_file():
        return _mp3d(house, path.with_name(scan + "_semantic.ply"), to_world, vertices_w, triangles)
    txt, sem = path.with_name(scan + ".semantic.txt"), path.with_name(scan + ".semantic.glb")
    if txt.is_file() and sem.is_file() and sem != path:
        return _hm3d(txt, sem, to_world, vertices_w, triangles)
    return None


# --- Matterport3D ----------------------------------------------------------------------------------


@dataclass
class House:
    levels: int
    regions: list[tuple[int, int, str, np.ndarray, np.ndarray]]  # index, level, label code, lo, hi
    categories: dict[int, str]  # category index -> mpcat40 name
    objects: list[tuple[int, int, int, np.ndarray, np.ndarray, np.ndarray]]  # index, region, category, centre, axes (3,3), radii
    segments: dict[int, int]  # segment id -> object index


def read_house(path: Path) -> House:
    """Parse the lines of a Matterport ``.house`` file that carry labels (levels, regions, categories, objects, segments)."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    if not lines or not lines[0].startswith("ASCII 1.1"):
        raise SceneFormatError(f"{path}: not a Matterport house file (first line {lines[:1]})")
    levels, regions, cats, objs, segs = 0, [], {}, [], {}
    try:
        for ln in lines[1:]:
            f = ln.split()
            if not f:
                continue
            kind = f[0]
            if kind == "L":
                levels += 1
            elif kind == "R":
                regions.append((int(f[1]), int(f[2]), f[5], np.array(f[9:12], float), np.array(f[12:15], float)))
            elif kind == "C":
                # C index mapping_index mapping_name mpcat40_index mpcat40_name ...; names use '#' for spaces
                cats[int(f[1])] = f[5].replace("#", " ").replace("_", " ")
            elif kind == "O":
                a0, a1 = np.array(f[7:10], float), np.array(f[10:13], float)
                axes = np.stack([a0, a1, np.cross(a0, a1)])
                objs.append((int(f[1]), int(f[2]), int(f[3]), np.array(f[4:7], float), axes, np.abs(np.array(f[13:16], float))))
            elif kind == "E":
                segs[int(f[3])] = int(f[2])
    except (IndexError, ValueError) as exc:
        raise SceneFormatError(f"{path}: malformed line ({exc})") from None
    return House(max(levels, 1), regions, cats, objs, segs)


def _mp3d(house_path: Path, semantic_ply: Path, to_world, vertices_w, triangles) -> SceneSemantics:
    house = read_house(house_path)
    names = sorted({house.categories.get(o[2], "unknown") for o in house.objects})
    label_of_name = {n: i for i, n in enumerate(names)}
    obj_label = {o[0]: label_of_name[house.categories.get(o[2], "unknown")] for o in house.objects}
    centroids_w = vertices_w[triangles].mean(axis=1)
    source = str(house_path)
    if semantic_ply.is_file():
        sv, st, props = read_ply_faces(semantic_ply)
        if "object_id" in props:
            obj = props["object_id"]
        elif "segment_id" in props:
            obj = np.array([house.segments.get(int(s), -1) for s in props["segment_id"]])
        else:
            obj = None
        if obj is not None:
            lut = np.array([obj_label.get(int(o), -1) for o in range(int(obj.max()) + 1)] if obj.max() >= 0 else [-1], np.int32)
            sem_labels = np.where(obj >= 0, lut[np.clip(obj, 0, len(lut) - 1)], -1)
        elif "category_id" in props:
            cat_label = {k: label_of_name.get(v, -1) for k, v in house.categories.items()}
            sem_labels = np.array([cat_label.get(int(c), -1) for c in props["category_id"]], np.int32)
        else:
            raise SceneFormatError(f"{semantic_ply}: faces carry none of object_id, segment_id, category_id")
        labels = transfer_labels(sv @ to_world.T, st, sem_labels, centroids_w)
        source += f" + {semantic_ply.name}"
    else:
        labels = _labels_from_boxes(house, obj_label, centroids_w @ np.linalg.inv(to_world).T, len(triangles))
    rooms, room_of_region = _rooms(house, to_world)
    objects = []
    for idx, region, cat, centre, axes, radii in house.objects:
        name = house.categories.get(cat, "unknown")
        if name in STRUCTURE:
            continue
        corners = centre + (np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * radii) @ axes
        cw = corners @ to_world.T
        lo, hi = cw.min(axis=0), cw.max(axis=0)
        a0w = axes[0] @ to_world.T
        objects.append(SceneObject(
            object_id=idx, label=name, colour="", room=room_of_region.get(region, ""),
            position_m=(float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2), float(lo[2])),
            size_m=tuple(float(v) for v in hi - lo), yaw_rad=float(math.atan2(a0w[1], a0w[0])),
        ))
    return SceneSemantics(labels, dict(enumerate(names)), rooms, objects, house.levels, source)


def _rooms(house: House, to_world: np.ndarray) -> tuple[list[Room], dict[int, str]]:
    rooms, count, room_of_region = [], {}, {}
    for idx, level, code, lo, hi in house.regions:
        rtype = MP3D_REGION_TYPES.get(code, "room")
        count[rtype] = count.get(rtype, 0) + 1
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) @ to_world.T
        wl, wh = corners.min(axis=0), corners.max(axis=0)
        name = f"{rtype} {count[rtype]}"
        room_of_region[idx] = name
        rooms.append(Room(name, rtype, level, (float(wl[0]), float(wl[1])), (float(wh[0]), float(wh[1])), float(wl[2])))
    return rooms, room_of_region


def _labels_from_boxes(house: House, obj_label: dict[int, int], centroids_f: np.ndarray, n: int) -> np.ndarray:
    """Each triangle takes the label of the smallest object box (file frame) that holds its centroid."""
    from scipy.spatial import cKDTree

    labels = np.full(n, -1, np.int32)
    best = np.full(n, np.inf)
    tree = cKDTree(centroids_f)
    for idx, _, _, centre, axes, radii in house.objects:
        cand = np.asarray(tree.query_ball_point(centre, float(np.linalg.norm(radii)) + 1e-6), dtype=np.int64)
        if cand.size == 0:
            continue
        local = np.abs((centroids_f[cand] - centre) @ axes.T)
        inside = cand[np.all(local <= radii + 1e-6, axis=1)]
        vol = float(np.prod(radii))
        take = inside[vol < best[inside]]
        labels[take] = obj_label[idx]
        best[take] = vol
    return labels


# --- HM3D-Semantics --------------------------------------------------------------------------------

_HEX = re.compile(r"^[0-9a-fA-F]{6}$")


def read_hm3d_semantic_txt(path: Path) -> dict[int, tuple[int, str, int]]:
    """``rgb (0xRRGGBB) -> (object id, category, region)`` from an HM3D ``*.semantic.txt``."""
    out: dict[int, tuple[int, str, int]] = {}
    with open(path, encoding="utf-8", errors="replace", newline="") as f:
        for row in csv.reader(f):
            if len(row) < 4 or not _HEX.match(row[1].strip()):
                continue  # the header line ("HM3D Semantic Annotations") and blank lines
            try:
                out[int(row[1].strip(), 16)] = (int(row[0]), row[2].strip().strip('"'), int(row[3]))
            except ValueError:
                raise SceneFormatError(f"{path}: malformed line {row}") from None
    if not out:
        raise SceneFormatError(f"{path}: no 'id,HEX,\"category\",region' lines")
    return out


def _hm3d(txt: Path, sem_path: Path, to_world, vertices_w, triangles) -> SceneSemantics:
    table = read_hm3d_semantic_txt(txt)
    sem = read_mesh_file(sem_path)
    rgb = semantic_triangle_rgb(sem)
    key = (rgb[:, 0].astype(np.int64) << 16) | (rgb[:, 1].astype(np.int64) << 8) | rgb[:, 2].astype(np.int64)
    names = sorted({v[1] for v in table.values()})
    label_of_name = {n: i for i, n in enumerate(names)}
    keys = np.array(sorted(table), np.int64)
    pos = np.clip(np.searchsorted(keys, key), 0, len(keys) - 1)
    hit = keys[pos] == key
    obj_ids = np.where(hit, np.array([table[int(k)][0] for k in keys])[pos], -1)
    sem_labels = np.where(hit, np.array([label_of_name[table[int(k)][1]] for k in keys])[pos], -1).astype(np.int32)
    sv_w = sem.vertices @ to_world.T
    centroids_w = vertices_w[triangles].mean(axis=1)
    labels = transfer_labels(sv_w, sem.triangles, sem_labels, centroids_w)
    objects = _objects_from_triangles(sv_w, sem.triangles, obj_ids, {v[0]: v[1] for v in table.values()})
    return SceneSemantics(labels, dict(enumerate(names)), [], objects, 1, f"{sem_path.name} + {txt.name}")


def semantic_triangle_rgb(mesh) -> np.ndarray:
    """(T, 3) uint8 colour of each triangle of a flat-painted semantic mesh: the texel under its UV
    centroid (nearest, no filtering) or its first vertex's colour."""
    tris = mesh.triangles
    rgb = np.round(np.clip(mesh.vertex_colors[tris[:, 0]], 0, 1) * 255).astype(np.uint8)
    if mesh.images:
        uv = mesh.triangle_uvs.mean(axis=1)
        for k, img in enumerate(mesh.images):
            sel = mesh.material_ids == k
            if not sel.any():
                continue
            h, w = img.shape[:2]
            u = uv[sel, 0] - np.floor(uv[sel, 0])
            v = uv[sel, 1] - np.floor(uv[sel, 1])
            rgb[sel] = img[np.clip(((1 - v) * h).astype(int), 0, h - 1), np.clip((u * w).astype(int), 0, w - 1)]
    return rgb


def _objects_from_triangles(vw, tris, obj_ids, category) -> list[SceneObject]:
    valid = obj_ids >= 0
    if not valid.any():
        return []
    ids = obj_ids[valid]
    pts = vw[tris[valid]]  # (S, 3, 3)
    uniq, inv = np.unique(ids, return_inverse=True)
    lo = np.full((len(uniq), 3), np.inf)
    hi = np.full((len(uniq), 3), -np.inf)
    np.minimum.at(lo, inv, pts.min(axis=1))
    np.maximum.at(hi, inv, pts.max(axis=1))
    out = []
    for k, oid in enumerate(uniq):
        name = category.get(int(oid), "unknown")
        if name in STRUCTURE:
            continue
        out.append(SceneObject(object_id=int(oid), label=name, colour="", room="",
                               position_m=(float((lo[k, 0] + hi[k, 0]) / 2), float((lo[k, 1] + hi[k, 1]) / 2), float(lo[k, 2])),
                               size_m=tuple(float(v) for v in hi[k] - lo[k])))
    return out


# --- shared helpers ---------------------------------------------------------------------------------


def transfer_labels(sem_vertices_w, sem_triangles, sem_labels, points_w) -> np.ndarray:
    """The label of the semantic triangle nearest each point (Embree closest-point queries)."""
    from shared.o3d import o3d  # here, not at module level: open3d costs ~0.4 s of CPU at every process start

    rc = o3d.t.geometry.RaycastingScene()
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(sem_vertices_w, dtype=np.float32))
    m.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(sem_triangles, dtype=np.int32))
    rc.add_triangles(m)
    prim = rc.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(points_w, dtype=np.float32)))["primitive_ids"].numpy()
    lab = np.append(np.asarray(sem_labels, dtype=np.int32), np.int32(-1))
    return lab[np.minimum(prim.astype(np.int64), len(lab) - 1)]


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply_faces(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Vertices (N, 3), triangles (T, 3) and every scalar face property of a triangle PLY.

    open3d drops per-face properties, and they are what a semantic PLY is for.
    """
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise SceneFormatError(f"{path}: not a PLY file")
        fmt, elements = None, []
        while True:
            line = f.readline()
            if not line:
                raise SceneFormatError(f"{path}: PLY header has no end_header")
            t = line.decode("ascii", "replace").split()
            if not t or t[0] in ("comment", "obj_info"):
                continue
            if t[0] == "format":
                fmt = t[1]
            elif t[0] == "element":
                elements.append((t[1], int(t[2]), []))
            elif t[0] == "property":
                elements[-1][2].append(tuple(t[1:]))
            elif t[0] == "end_header":
                break
        body = f.read()
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SceneFormatError(f"{path}: PLY format {fmt!r}")
    end = "<" if fmt == "binary_little_endian" else ">"
    out: dict[str, np.ndarray] = {}
    offset = 0
    text_rows = body.decode("ascii", "replace").split("\n") if fmt == "ascii" else None
    row = 0
    for name, count, props in elements:
        if fmt == "ascii":
            rows = [r.split() for r in text_rows[row : row + count]]
            row += count
            out[name] = _ascii_element(props, rows, path)
            continue
        fields = []
        for p in props:
            if p[0] == "list":
                # Semantic meshes are all triangles (or all quads, as Habitat accepts): a fixed-length list
                # lets numpy read the element in one go. The first count tells which.
                at = offset + (np.dtype(fields).itemsize if fields else 0)
                k = int(np.frombuffer(body, end + _PLY_TYPES[p[1]], count=1, offset=at)[0]) if count and at < len(body) else 3
                if k not in (3, 4):
                    raise SceneFormatError(f"{path}: faces of {k} vertices (only triangles and quads)")
                fields += [(p[3] + "_n", end + _PLY_TYPES[p[1]]), (p[3], end + _PLY_TYPES[p[2]], (k,))]
            else:
                fields.append((p[1], end + _PLY_TYPES[p[0]]))
        dt = np.dtype(fields)
        try:
            arr = np.frombuffer(body, dtype=dt, count=count, offset=offset)
        except ValueError:
            raise SceneFormatError(f"{path}: PLY body shorter than its header says") from None
        offset += dt.itemsize * count
        out[name] = arr
    try:
        vert = out["vertex"]
        face = out["face"]
        v = np.stack([np.asarray(vert[k], np.float64) for k in ("x", "y", "z")], axis=1)
        key = "vertex_indices" if "vertex_indices" in face.dtype.names else "vertex_index"
        idx = np.asarray(face[key], np.int64)
        k = idx.shape[1]
        if np.any(face[key + "_n"] != k):
            raise SceneFormatError(f"{path}: faces mix triangles and quads")
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneFormatError(f"{path}: PLY lacks vertex x/y/z or face vertex_indices ({exc})") from None
    props = {n: np.asarray(face[n]) for n in face.dtype.names if n not in (key, key + "_n")}
    if k == 4:  # quad [0, 1, 2, 3] -> triangles [0, 1, 2], [0, 2, 3], each keeping the quad's properties
        idx = np.stack([idx[:, [0, 1, 2]], idx[:, [0, 2, 3]]], axis=1).reshape(-1, 3)
        props = {n: np.repeat(a, 2) for n, a in props.items()}
    tris = idx.astype(np.int32)
    if len(tris) and (tris.min() < 0 or tris.max() >= len(v)):
        raise SceneFormatError(f"{path}: face indices out of range")
    return v, tris, props


def _ascii_element(props, rows, path) -> np.ndarray:
    fields = []
    for p in props:
        if p[0] == "list":
            before = props.index(p)  # the scalars before the list, one token each
            k = int(rows[0][before]) if rows and len(rows[0]) > before else 3
            fields += [(p[3] + "_n", "i8"), (p[3], "i8", (k,))]
        else:
            fields.append((p[1], _PLY_TYPES[p[0]]))
    arr = np.zeros(len(rows), dtype=np.dtype(fields))
    try:
        for i, r in enumerate(rows):
            j = 0
            for p in props:
                if p[0] == "list":
                    n = int(r[j])
                    arr[i][p[3] + "_n"] = n
                    k = arr.dtype[p[3]].shape[0]
                    arr[i][p[3]] = [int(x) for x in r[j + 1 : j + 1 + min(n, k)]] + [0] * (k - min(n, k))
                    j += 1 + n
                else:
                    arr[i][p[1]] = float(r[j])
                    j += 1
    except (IndexError, ValueError) as exc:
        raise SceneFormatError(f"{path}: malformed ASCII PLY row ({exc})") from None
    return arr
