"""Scenes: a triangle mesh with colours (vertex colours or a texture), labels and a floor plan.

A :class:`Scene` is what the simulator renders and what the navigation grid is built from. It comes
either from the procedural house generator (:mod:`.house`, labelled rooms and objects) or from any
mesh file open3d reads (``.ply``, ``.obj``, ``.glb``; labels unknown, ``-1``).

Scene specs (the ``scene`` field of the simulator config, the ``scene_id`` of an episode):

* ``generated:<seed>`` or ``generated:<seed>:floors=2:area=200`` - a procedural house;
* a path to a mesh file, absolute or relative to the configured scenes directory.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from shared.schemas import Pose

from .errors import SceneFormatError, SceneNotFoundError

log = logging.getLogger(__name__)

GENERATED_PREFIX = "generated:"


@dataclass(frozen=True)
class Room:
    """A room of a floor plan: an axis-aligned box on the floor of storey ``floor``."""

    name: str  # unique, e.g. "bedroom 2"
    room_type: str  # bedroom, kitchen, bathroom, living room, hallway, office, dining room, staircase
    floor: int
    min_xy_m: tuple[float, float]
    max_xy_m: tuple[float, float]
    floor_z_m: float = 0.0

    @property
    def area_m2(self) -> float:
        return (self.max_xy_m[0] - self.min_xy_m[0]) * (self.max_xy_m[1] - self.min_xy_m[1])

    @property
    def centre_m(self) -> np.ndarray:
        return np.array(
            [
                (self.min_xy_m[0] + self.max_xy_m[0]) / 2.0,
                (self.min_xy_m[1] + self.max_xy_m[1]) / 2.0,
                self.floor_z_m,
            ]
        )

    def contains(self, p: np.ndarray, z_tol_m: float = 1.0) -> bool:
        p = np.asarray(p, dtype=np.float64)
        return bool(
            self.min_xy_m[0] <= p[0] <= self.max_xy_m[0]
            and self.min_xy_m[1] <= p[1] <= self.max_xy_m[1]
            and abs(p[2] - self.floor_z_m) <= z_tol_m
        )


@dataclass(frozen=True)
class SceneObject:
    """A piece of furniture: class label, colour name (for instructions), room and box."""

    object_id: int
    label: str
    colour: str
    room: str
    position_m: tuple[float, float, float]  # centre of the footprint, on the floor
    size_m: tuple[float, float, float]  # extent along world x, y, z
    yaw_rad: float = 0.0

    @property
    def description(self) -> str:
        return f"{self.colour} {self.label}" if self.colour else self.label


@dataclass
class Texture:
    """Texture lookup data: per-corner UVs (T, 3, 2), per-triangle image index, images (H, W, 3) uint8."""

    triangle_uvs: np.ndarray
    material_ids: np.ndarray
    images: list[np.ndarray]


@dataclass
class Scene:
    """A renderable, navigable scene (world frame: metres, z up).

    ``triangle_labels[i]`` indexes ``label_names`` (``-1`` = unknown). Colours are float32 in [0, 1].
    """

    name: str
    vertices: np.ndarray  # (N, 3) float64
    triangles: np.ndarray  # (T, 3) int32
    vertex_colors: np.ndarray  # (N, 3) float32 in [0, 1]
    triangle_labels: np.ndarray  # (T,) int32
    label_names: dict[int, str] = field(default_factory=dict)
    rooms: list[Room] = field(default_factory=list)
    objects: list[SceneObject] = field(default_factory=list)
    start_pose: Pose | None = None
    texture: Texture | None = None
    source: str = ""
    floors: int = 1
    # True when every triangle is wound counter-clockwise seen from outside (generated scenes);
    # scans often mix windings, so "which way a face looks" is then unknown.
    consistent_winding: bool = False

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32)
        self.vertex_colors = np.ascontiguousarray(self.vertex_colors, dtype=np.float32)
        self.triangle_labels = np.ascontiguousarray(self.triangle_labels, dtype=np.int32)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise SceneFormatError(f"vertices must be (N, 3), got {self.vertices.shape}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3 or len(self.triangles) == 0:
            raise SceneFormatError(f"scene {self.name!r} has no triangles")
        if self.vertex_colors.shape != self.vertices.shape:
            raise SceneFormatError("vertex_colors must match vertices")
        if self.triangle_labels.shape != (len(self.triangles),):
            raise SceneFormatError("triangle_labels must have one entry per triangle")

    # --- queries ---------------------------------------------------------------------------------

    @property
    def bounds_m(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def label_id(self, name: str) -> int:
        for k, v in self.label_names.items():
            if v == name:
                return k
        raise KeyError(name)

    def room_at(self, p) -> Room | None:
        """The room containing floor point ``p`` (the one whose floor is nearest below it)."""
        p = np.asarray(p, dtype=np.float64)
        best, best_dz = None, np.inf
        for r in self.rooms:
            if r.contains(p, z_tol_m=1.5):
                dz = abs(p[2] - r.floor_z_m)
                if dz < best_dz:
                    best, best_dz = r, dz
        return best

    def room(self, name: str) -> Room:
        for r in self.rooms:
            if r.name == name:
                return r
        raise KeyError(name)

    def to_legacy_mesh(self) -> o3d.geometry.TriangleMesh:
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors.astype(np.float64))
        return mesh

    def export_ply(self, path: Path | str) -> Path:
        """Write the mesh (vertices, triangles, vertex colours) as a binary .ply."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not o3d.io.write_triangle_mesh(str(path), self.to_legacy_mesh(), write_ascii=False):
            raise SceneFormatError(f"could not write {path}")
        return path


# --- loading -------------------------------------------------------------------------------------


def is_generated_spec(spec: str) -> bool:
    return spec.startswith(GENERATED_PREFIX)


#: Procedural scene builders by spec prefix. The house generator registers ``generated:`` when it is
#: imported (the package's ``__init__`` does that), so this module never imports it: no import cycle.
SCENE_BUILDERS: dict[str, Callable[[str], Scene]] = {}


def register_scene_builder(prefix: str, build: Callable[[str], Scene]) -> None:
    SCENE_BUILDERS[prefix] = build


def resolve_scene_path(spec: str, scenes_dir: Path | str | None = None) -> Path:
    """Resolve a mesh path: absolute, or relative to ``scenes_dir``; missing -> SceneNotFoundError."""
    p = Path(spec).expanduser()
    candidates = [p] if p.is_absolute() else []
    if not p.is_absolute():
        if scenes_dir is not None:
            candidates.append(Path(scenes_dir).expanduser() / p)
        candidates.append(p)
    for c in candidates:
        if c.is_file():
            return c
    raise SceneNotFoundError(candidates[0], scenes_dir)


def load_scene(spec: str, scenes_dir: Path | str | None = None) -> Scene:
    """Build or load the scene named by ``spec`` (see the module docstring)."""
    for prefix, build in SCENE_BUILDERS.items():
        if spec.startswith(prefix):
            return build(spec)
    return load_mesh_scene(resolve_scene_path(spec, scenes_dir))


def load_mesh_scene(path: Path | str) -> Scene:
    """Load any mesh open3d reads, with vertex colours or a texture; labels are unknown (-1)."""
    path = Path(path)
    if not path.is_file():
        raise SceneNotFoundError(path, None)
    mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False)
    if not mesh.has_triangles():
        # read_triangle_mesh returns an empty mesh rather than raising on unreadable files
        raise SceneFormatError(f"{path} holds no triangle mesh open3d can read")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int32)
    if mesh.has_vertex_colors():
        colors = np.asarray(mesh.vertex_colors, dtype=np.float32)
    else:
        colors = np.full_like(vertices, 0.7, dtype=np.float32)
    texture = None
    if mesh.has_triangle_uvs() and mesh.has_textures():
        images = [_image_rgb(np.asarray(t)) for t in mesh.textures]
        images_ok = [im for im in images if im.size > 0]
        if images_ok:
            uvs = np.asarray(mesh.triangle_uvs, dtype=np.float32).reshape(-1, 3, 2)
            if mesh.has_triangle_material_ids():
                mids = np.asarray(mesh.triangle_material_ids, dtype=np.int32)
            else:
                mids = np.zeros(len(triangles), dtype=np.int32)
            # Materials without an image fall back to vertex colours (index -1).
            mids = np.where((mids >= 0) & (mids < len(images)), mids, -1)
            valid = np.array([im.size > 0 for im in images])
            mids = np.where(mids >= 0, np.where(valid[np.clip(mids, 0, None)], mids, -1), -1)
            texture = Texture(uvs, mids.astype(np.int32), [im if im.size else np.zeros((1, 1, 3), np.uint8) for im in images])
    log.info("loaded %s: %d vertices, %d triangles, texture=%s", path, len(vertices), len(triangles), texture is not None)
    return Scene(
        name=path.stem,
        vertices=vertices,
        triangles=triangles,
        vertex_colors=colors,
        triangle_labels=np.full(len(triangles), -1, dtype=np.int32),
        texture=texture,
        source=str(path),
    )


def _image_rgb(img: np.ndarray) -> np.ndarray:
    if img.size == 0:
        return np.zeros((0, 0, 3), np.uint8)
    if img.dtype != np.uint8:
        scale = 255.0 if img.dtype.kind == "f" else 255.0 / np.iinfo(img.dtype).max
        img = np.clip(img.astype(np.float32) * scale, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])
