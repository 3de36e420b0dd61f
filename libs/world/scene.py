"""Scenes: a triangle mesh with colours (vertex colours or a texture), labels and a floor plan.

A :class:`Scene` is what the simulator renders and what the navigation grid is built from. It comes
either from the procedural house generator (:mod:`.house`, labelled rooms and objects) or from any
mesh file open3d reads (``.ply``, ``.obj``, ``.glb``; labels where the dataset ships them, else ``-1``).

Scene specs (the ``scene`` field of the simulator config, the ``scene_id`` of an episode):

* ``generated:<seed>`` or ``generated:<seed>:floors=2:area=200`` - a procedural house;
* a path to a mesh file, absolute or relative to the configured scenes directory, optionally
  with frame options: ``chair.glb:up=y``, ``scan.ply:up=z:scale=0.001`` (:mod:`.scene_files`
  decides a file's frame and reads its colours; :mod:`.scene_semantics` its labels).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.schemas import Pose

from .errors import SceneFormatError, SceneNotFoundError
from .scene_layout import Room, SceneObject
from .scene_files import SceneFrame, read_mesh_file, resolve_frame, scan_name, split_scene_spec

if TYPE_CHECKING:
    import open3d as o3d

log = logging.getLogger(__name__)

GENERATED_PREFIX = "generated:"


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
        from shared.o3d import o3d  # here, not at module level: open3d costs ~0.4 s of CPU at every process start

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors.astype(np.float64))
        return mesh

    def export_ply(self, path: Path | str) -> Path:
        """Write the mesh (vertices, triangles, vertex colours) as a binary .ply."""
        from shared.o3d import o3d  # here, not at module level (see to_legacy_mesh)

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


def load_scene(spec: str, scenes_dir: Path | str | None = None, frame: Mapping[str, Any] | SceneFrame | None = None) -> Scene:
    """Build or load the scene named by ``spec`` (see the module docstring).

    A mesh spec may carry frame options (``x.glb:up=z:scale=0.01``, see :mod:`.scene_files`);
    ``frame`` overrides them in turn.
    """
    for prefix, build in SCENE_BUILDERS.items():
        if spec.startswith(prefix):
            return build(spec)
    path_spec, options = split_scene_spec(spec)
    if isinstance(frame, SceneFrame):
        frame = frame.model_dump(exclude_unset=True)
    return load_mesh_scene(resolve_scene_path(path_spec, scenes_dir), {**options, **(frame or {})} or None)


def load_mesh_scene(path: Path | str, frame: Mapping[str, Any] | SceneFrame | None = None) -> Scene:
    """Load a mesh file upright, in metres and in its colours; labels where the dataset ships them.

    The frame comes from :func:`.scene_files.resolve_frame` (``frame`` overrides what the file's
    configs and the rules say); colours from :func:`.scene_files.read_mesh_file`; semantics (MP3D
    ``.house``, HM3D ``.semantic.glb`` + ``.semantic.txt``) from :mod:`.scene_semantics`.
    """
    from .scene_semantics import load_semantics

    path = Path(path)
    if not path.is_file():
        raise SceneNotFoundError(path, None)
    resolved = resolve_frame(path, frame)
    data = read_mesh_file(path)
    to_world = resolved.frame.matrix()
    vertices = data.vertices @ to_world.T
    texture = None
    if data.images:
        texture = Texture(data.triangle_uvs, data.material_ids, data.images)
    labels = np.full(len(data.triangles), -1, dtype=np.int32)
    sem = load_semantics(path, to_world, vertices, data.triangles)
    log.info("loaded %s: %d vertices, %d triangles, %d materials, texture=%s, frame from %s, semantics=%s",
             path, len(vertices), len(data.triangles), data.materials, texture is not None, resolved.source,
             sem.source if sem else None)
    return Scene(
        name=scan_name(path),
        vertices=vertices,
        triangles=data.triangles,
        vertex_colors=data.vertex_colors,
        triangle_labels=sem.triangle_labels if sem else labels,
        label_names=sem.label_names if sem else {},
        rooms=sem.rooms if sem else [],
        objects=sem.objects if sem else [],
        texture=texture,
        source=str(path),
        floors=sem.floors if sem else 1,
    )
