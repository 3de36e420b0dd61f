"""Scene files: which way up a file is, in which units, and what colour it is.

**One place decides a scene file's frame** (:func:`resolve_frame`), first match wins:

1. an explicit frame: the ``frame`` argument of :func:`~.scene.load_mesh_scene`, or options in the
   scene spec (``chair.glb:up=y``, ``scan.glb:up=z:front=y:scale=0.01``,
   ``x.glb:stage_config=/path/x.stage_config.json``), which is how a config names a per-scene override;
2. a Habitat stage config beside the file (``<name>.stage_config.json``, or any
   ``*.stage_config.json`` there whose ``render_asset`` is the file): ``up``, ``front``, ``scale``,
   ``units_to_meters``;
3. a Habitat scene dataset config (``*.scene_dataset_config.json``) in the file's folder or up to
   three folders above it: its ``stages.default_attributes`` (how MP3D / HM3D downloads declare it);
4. :data:`FRAME_RULES`, a table keyed by file name and folder: ``.glb`` / ``.gltf`` are glTF's y-up,
   except ``.glb`` scans under an ``mp3d/`` or ``hm3d/`` folder (and HM3D's ``*.basis.glb``), which
   Habitat loads with gravity along -z (habitat-sim ``AssetInfo::fromPath``: "assumes MP3D glb with
   gravity = -Z"); ``.ply`` is z-up (Replica, ScanNet); anything else is taken as stored (z-up).

The frame becomes a matrix with :func:`shared.geometry.scene_file_to_world`, which by construction is
``habitat_to_world`` after Habitat's own transform of the file; so R2R-CE positions (Habitat frame)
land where Habitat puts them relative to the mesh.

**Colours** (:func:`read_mesh_file`): glTF files through :mod:`.gltf` (node transforms, every
primitive), OBJ / FBX / DAE through open3d's ``read_triangle_model``: a material's base-colour
texture with the mesh's UVs, its base-colour factor (multiplied into the texture, as glTF specifies),
vertex colours where the file has them; ``.ply`` keeps its vertex colours. Several materials per scene are fine: the simulator's shading
tables index one image per material.
"""

from __future__ import annotations

import fnmatch
import json
import logging
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from shared.geometry import habitat_alignment, scene_file_to_world

from .errors import SceneFormatError
from .gltf import Part, read_gltf

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]


class SceneFrame(BaseModel):
    """How a scene file's axes and units relate to the world (Habitat's stage attributes).

    ``up`` and ``front`` are the file's own up and front directions; ``scale`` (per file axis) and
    ``units_to_meters`` multiply the coordinates. The default is Habitat's (and glTF's) frame.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    up: Vec3 = (0.0, 1.0, 0.0)
    front: Vec3 = (0.0, 0.0, -1.0)
    scale: Vec3 = (1.0, 1.0, 1.0)
    units_to_meters: float = Field(1.0, gt=0.0, allow_inf_nan=False)

    @field_validator("up", "front", "scale", mode="before")
    @classmethod
    def _vector(cls, v: Any) -> Any:
        if isinstance(v, str):
            return parse_vector(v)
        if isinstance(v, (int, float)):
            return (float(v),) * 3  # a uniform scale
        return v

    @model_validator(mode="after")
    def _check(self) -> SceneFrame:
        for name in ("up", "front", "scale"):
            if not all(math.isfinite(c) for c in getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)}")
        if min(self.scale) <= 0:
            raise ValueError(f"scale must be positive (a mirrored scene is not a scene), got {self.scale}")
        habitat_alignment(self.up, self.front)  # raises on zero or parallel vectors
        return self

    def matrix(self) -> np.ndarray:
        """3x3 file -> world (z up, metres)."""
        return scene_file_to_world(self.up, self.front, np.asarray(self.scale) * self.units_to_meters)

    def with_override(self, override: Mapping[str, Any] | SceneFrame | None) -> SceneFrame:
        """This frame with the fields ``override`` sets; a new ``up`` without a ``front`` keeps the old
        front when it is still perpendicular, else takes the usual one for that up axis."""
        if override is None:
            return self
        fields = override.model_dump(exclude_unset=True) if isinstance(override, SceneFrame) else dict(override)
        try:
            if "up" in fields and "front" not in fields:
                up = SceneFrame(up=fields["up"], front=_default_front(fields["up"])).up
                if abs(float(np.dot(_unit(up), _unit(self.front)))) > 1e-6:
                    fields["front"] = _default_front(up)
            return SceneFrame(**{**self.model_dump(), **fields})
        except ValidationError as exc:
            raise SceneFormatError(f"bad scene frame override {fields}: {exc.errors()[0]['msg']}") from None


GLTF_Y_UP = SceneFrame()  # glTF 2.0 and Habitat's default: +y up, front -z
Z_UP = SceneFrame(up=(0.0, 0.0, 1.0), front=(0.0, 1.0, 0.0))  # maps to the world unchanged


@dataclass(frozen=True)
class FrameRule:
    """Files whose lower-cased name matches ``name_glob`` (and, if given, that lie under a folder
    whose name starts with ``under``: ``mp3d``, ``mp3d_example``, ``mp3d_habitat``) are in ``frame``;
    ``why`` is the convention it follows."""

    name_glob: str
    frame: SceneFrame
    why: str
    under: str | None = None

    def matches(self, path: Path) -> bool:
        if not fnmatch.fnmatchcase(path.name.lower(), self.name_glob):
            return False
        return self.under is None or any(p.lower().startswith(self.under) for p in path.parent.parts)


FRAME_RULES: tuple[FrameRule, ...] = (
    FrameRule("*.glb", Z_UP, "Matterport3D in Habitat: gravity along -z", under="mp3d"),
    FrameRule("*.glb", Z_UP, "HM3D in Habitat: gravity along -z (Habitat's .glb stage default)", under="hm3d"),
    FrameRule("*.basis.glb", Z_UP, "HM3D (Basis-texture build) in Habitat: gravity along -z"),
    FrameRule("*.glb", GLTF_Y_UP, "glTF 2.0: +y up, metres"),
    FrameRule("*.gltf", GLTF_Y_UP, "glTF 2.0: +y up, metres"),
    FrameRule("*.ply", Z_UP, "PLY scans (Replica, ScanNet): z up, metres"),
    FrameRule("*", Z_UP, "taken as stored: z up, metres"),
)

FRAME_KEYS = ("up", "front", "scale", "units_to_meters")
STAGE_CONFIG_SUFFIX = ".stage_config.json"
DATASET_CONFIG_SUFFIX = ".scene_dataset_config.json"
_DATASET_CONFIG_LEVELS = 4  # the file's folder and three above it: hm3d/<split>/<scene>/<scene>.glb


@dataclass(frozen=True)
class ResolvedFrame:
    frame: SceneFrame
    source: str  # what decided it, for logs and the scene summary


def resolve_frame(path: Path | str, override: Mapping[str, Any] | SceneFrame | None = None) -> ResolvedFrame:
    """The frame of scene file ``path`` (see the module docstring for the order)."""
    path = Path(path)
    override = dict(override) if isinstance(override, Mapping) else override
    stage_cfg = None
    if isinstance(override, dict) and "stage_config" in override:
        stage_cfg = Path(override.pop("stage_config")).expanduser()
        if not stage_cfg.is_file():
            raise SceneFormatError(f"stage config {stage_cfg} does not exist")
    if isinstance(override, SceneFrame) and not override.model_fields_set:
        override = None
    base: ResolvedFrame | None = None
    if stage_cfg is not None:
        base = ResolvedFrame(read_stage_config(stage_cfg), str(stage_cfg))
    if base is None:
        found = find_stage_config(path)
        if found is not None:
            base = ResolvedFrame(read_stage_config(found), str(found))
    if base is None:
        found = find_dataset_config(path)
        if found is not None:
            frame = read_dataset_stage_defaults(found)
            if frame is not None:
                base = ResolvedFrame(frame, str(found))
    if base is None:
        rule = next(r for r in FRAME_RULES if r.matches(path))
        base = ResolvedFrame(rule.frame, f"rule {rule.name_glob}{' under ' + rule.under + '/' if rule.under else ''}: {rule.why}")
    if override:
        return ResolvedFrame(base.frame.with_override(override), f"explicit override on {base.source}")
    return base


def scan_name(path: Path) -> str:
    """The scan a file belongs to: its stem without HM3D's ``.basis`` (``abc.basis.glb`` -> ``abc``)."""
    stem = path.stem
    return stem[: -len(".basis")] if stem.lower().endswith(".basis") else stem


def find_stage_config(path: Path) -> Path | None:
    """A Habitat stage config for ``path`` in its folder: by name first, then by ``render_asset``."""
    names = [path.stem + STAGE_CONFIG_SUFFIX, scan_name(path) + STAGE_CONFIG_SUFFIX]
    for n in dict.fromkeys(names):
        c = path.with_name(n)
        if c.is_file():
            return c
    if not path.parent.is_dir():
        return None
    for c in sorted(path.parent.glob("*" + STAGE_CONFIG_SUFFIX)):
        doc = _read_json(c)
        if isinstance(doc, dict) and Path(str(doc.get("render_asset", ""))).name == path.name:
            return c
    return None


def find_dataset_config(path: Path) -> Path | None:
    """The nearest ``*.scene_dataset_config.json`` in the file's folder or the three above it."""
    folder = path.parent
    for _ in range(_DATASET_CONFIG_LEVELS):
        if folder.is_dir():
            hits = sorted(folder.glob("*" + DATASET_CONFIG_SUFFIX))
            if hits:
                return hits[0]
        if folder.parent == folder:
            break
        folder = folder.parent
    return None


def read_stage_config(path: Path | str) -> SceneFrame:
    """The frame a Habitat ``*.stage_config.json`` declares (missing keys keep Habitat's defaults)."""
    doc = _read_json(Path(path))
    if not isinstance(doc, dict):
        raise SceneFormatError(f"{path}: a stage config is a JSON object")
    return _frame_from_attributes(doc, path)


def read_dataset_stage_defaults(path: Path | str) -> SceneFrame | None:
    """``stages.default_attributes`` of a Habitat scene dataset config, or None when it sets no frame."""
    doc = _read_json(Path(path))
    attrs = doc.get("stages", {}).get("default_attributes", {}) if isinstance(doc, dict) else {}
    if not isinstance(attrs, dict) or not any(k in attrs for k in FRAME_KEYS):
        return None
    return _frame_from_attributes(attrs, path)


def _frame_from_attributes(attrs: dict, source) -> SceneFrame:
    origin = attrs.get("origin")
    if isinstance(origin, list) and any(float(c) != 0.0 for c in origin if isinstance(c, (int, float))):
        # Habitat offsets the stage by it; episode positions in such a dataset already include it.
        log.warning("%s: stage origin %s is not applied (only up, front, scale, units_to_meters are)", source, origin)
    fields = {k: attrs[k] for k in FRAME_KEYS if k in attrs}
    if "up" in fields and "front" not in fields:
        fields["front"] = _default_front(fields["up"])
    try:
        return SceneFrame(**fields)
    except ValidationError as exc:
        raise SceneFormatError(f"{source}: bad frame ({exc.errors()[0]['msg']})") from None


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneFormatError(f"{path}: not a readable JSON file ({exc})") from None


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _default_front(up) -> Vec3:
    """Habitat's pairing: z-up files face +y; every other up axis keeps front -z (or +y if that is up)."""
    u = _unit(parse_vector(up) if isinstance(up, str) else up)
    if abs(u[2]) > 0.9:
        return (0.0, 1.0, 0.0)
    return (0.0, 0.0, -1.0)


_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def parse_vector(text: str) -> Vec3:
    """``"y"``, ``"-z"``, ``"+x"`` or ``"0,0,1"``; a single number is a uniform scale."""
    t = text.strip().lower()
    sign = -1.0 if t.startswith("-") else 1.0
    axis = t.lstrip("+-")
    if axis in _AXES:
        return tuple(sign * c for c in _AXES[axis])  # type: ignore[return-value]
    try:
        parts = [float(p) for p in t.split(",")]
    except ValueError:
        raise SceneFormatError(f"not an axis or a vector: {text!r}") from None
    if len(parts) == 1:
        return (parts[0],) * 3  # type: ignore[return-value]
    if len(parts) != 3:
        raise SceneFormatError(f"a vector has 3 components, got {text!r}")
    return tuple(parts)  # type: ignore[return-value]


# --- scene specs with frame options --------------------------------------------------------------

SPEC_OPTIONS = (*FRAME_KEYS, "stage_config")


def split_scene_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """``"x.glb:up=y:scale=2"`` -> ``("x.glb", {"up": "y", "scale": "2"})``; unknown options raise."""
    head, opts = spec, {}
    while True:
        base, sep, tail = head.rpartition(":")
        key, eq, value = tail.partition("=")
        key = key.strip()
        if not sep or not eq or not re.fullmatch(r"[a-z_]+", key):
            break  # part of the path
        if key not in SPEC_OPTIONS:
            raise SceneFormatError(f"unknown scene option {key!r} in {spec!r} (known: {', '.join(SPEC_OPTIONS)})")
        opts[key] = value.strip()
        head = base
    if "units_to_meters" in opts:
        try:
            opts["units_to_meters"] = float(opts["units_to_meters"])
        except ValueError:
            raise SceneFormatError(f"units_to_meters must be a number in {spec!r}") from None
    return head, opts


# --- geometry and colours ------------------------------------------------------------------------


@dataclass
class MeshData:
    """A mesh file in its own frame: geometry, colours in [0, 1], and textures.

    ``material_ids[t]`` indexes ``images`` (-1: the triangle takes its vertex colours);
    ``triangle_uvs`` (T, 3, 2) are open3d's UVs (v up: image row = (1 - v) * height).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray
    triangle_uvs: np.ndarray | None = None
    material_ids: np.ndarray | None = None
    images: list[np.ndarray] | None = None
    materials: int = 0


GLTF_SUFFIXES = (".glb", ".gltf")  # our own reader (fast; see .gltf)
MODEL_SUFFIXES = (".obj", ".fbx", ".dae")  # formats with materials, through assimp


def read_mesh_file(path: Path | str) -> MeshData:
    """Read a mesh with its colours (see the module docstring); SceneFormatError if it holds none."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in GLTF_SUFFIXES:
        parts, materials = read_gltf(path)
        if not parts:
            raise SceneFormatError(f"{path} holds no triangles")
        return _assemble(path, parts, materials)
    if suffix in MODEL_SUFFIXES:
        from shared.o3d import o3d  # here, not at module level: ~0.4 s of CPU at every process start

        model = o3d.io.read_triangle_model(str(path))
        parts = [_o3d_part(model, m) for m in model.meshes if len(m.mesh.triangles) > 0]
        if parts:
            return _assemble(path, parts, len(model.materials))
    return _read_plain(path)


def _read_plain(path: Path) -> MeshData:
    from shared.o3d import o3d  # here, not at module level: open3d costs ~0.4 s of CPU at every process start

    mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False)
    if not mesh.has_triangles():
        # read_triangle_mesh returns an empty mesh rather than raising on unreadable files
        raise SceneFormatError(f"{path} holds no triangle mesh open3d can read")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    colors = np.asarray(mesh.vertex_colors, dtype=np.float32) if mesh.has_vertex_colors() else np.full_like(v, 0.7, dtype=np.float32)
    return MeshData(v, np.asarray(mesh.triangles, dtype=np.int32), colors)


def _o3d_part(model, part) -> Part:
    """An open3d (assimp) mesh as a Part: per-corner UVs become per-vertex by unsharing the corners."""
    mesh = part.mesh
    mat = model.materials[part.material_idx] if 0 <= part.material_idx < len(model.materials) else None
    v = np.asarray(mesh.vertices, dtype=np.float64)
    t = np.asarray(mesh.triangles, dtype=np.int32)
    colors = np.asarray(mesh.vertex_colors, dtype=np.float32) if mesh.has_vertex_colors() else None
    factor = np.clip(np.asarray(mat.base_color[:3], np.float32), 0, 1) if mat is not None else np.ones(3, np.float32)
    image, uvs = None, None
    if mat is not None and mat.albedo_img is not None and mesh.has_triangle_uvs() and np.asarray(mat.albedo_img).size:
        image = _image_rgb(np.asarray(mat.albedo_img))
        uvs = np.asarray(mesh.triangle_uvs, dtype=np.float32).reshape(-1, 2)
        v, colors = v[t.reshape(-1)], None if colors is None else colors[t.reshape(-1)]
        t = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    return Part(v, t, colors, uvs, factor, image, part.material_idx)


def _assemble(path: Path, parts: list[Part], materials: int) -> MeshData:
    """One mesh from several parts: vertex colours = COLOR_0 x factor, one image per material
    (factor baked in, as glTF multiplies them), per-corner UVs and per-triangle image ids."""
    verts, tris, cols, uvs, mids = [], [], [], [], []
    images: list[np.ndarray] = []
    image_of: dict[tuple[int, int], int] = {}
    offset = 0
    for part in parts:
        v, t = part.vertices, part.triangles
        c = part.colors if part.colors is not None else np.ones((len(v), 3), np.float32)
        c = c * part.factor
        uv = np.zeros((len(t), 3, 2), np.float32)
        mid = np.full(len(t), -1, np.int32)
        if part.image is not None and part.uvs is not None:
            key = (part.material, id(part.image))
            if key not in image_of:
                img = part.image
                if np.any(part.factor < 1.0):
                    # glTF: base colour = texel x factor; baked once so the shading stays a lookup.
                    img = np.clip(img.astype(np.float32) * part.factor + 0.5, 0, 255).astype(np.uint8)
                image_of[key] = len(images)
                images.append(img)
            k = image_of[key]
            uv = part.uvs[t]
            mid[:] = k
            # Vertex colours from the texels under each corner: what views that do not sample the
            # texture (colour means, coarse clouds) show instead of white.
            c = _texel_colors(images[k], uv, t, len(v))
        verts.append(v)
        tris.append(t + offset)
        cols.append(c)
        uvs.append(uv)
        mids.append(mid)
        offset += len(v)
    textured = bool(images)
    log.info("%s: %d primitives, %d materials, %d texture images", path.name, len(parts), materials, len(images))
    return MeshData(
        np.concatenate(verts), np.concatenate(tris).astype(np.int32), np.concatenate(cols).astype(np.float32),
        np.concatenate(uvs) if textured else None, np.concatenate(mids) if textured else None,
        images if textured else None, materials,
    )


def _texel_colors(img: np.ndarray, uv: np.ndarray, tris: np.ndarray, n_vertices: int) -> np.ndarray:
    h, w = img.shape[:2]
    u = uv[..., 0] - np.floor(uv[..., 0])
    v = uv[..., 1] - np.floor(uv[..., 1])
    px = np.clip((u * w).astype(np.int64), 0, w - 1)
    py = np.clip(((1.0 - v) * h).astype(np.int64), 0, h - 1)
    out = np.ones((n_vertices, 3), np.float32)
    out[tris.reshape(-1)] = img[py.reshape(-1), px.reshape(-1)].astype(np.float32) / 255.0
    return out


def _image_rgb(img: np.ndarray) -> np.ndarray:
    if img.size == 0:
        return np.zeros((1, 1, 3), np.uint8)
    if img.dtype != np.uint8:
        scale = 255.0 if img.dtype.kind == "f" else 255.0 / np.iinfo(img.dtype).max
        img = np.clip(img.astype(np.float32) * scale, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])
