"""Point clouds as they cross services: the type, its errors, and the project's one PLY layout.

Every service that holds a map speaks :class:`PointCloud`: the reconstructor builds and stores it, the
renderer draws it, the gateway streams it, the evaluation uploads curated ones. Files use ONE layout
(:func:`encode` / :func:`decode`): binary little-endian ``x y z`` float32, ``red green blue`` uchar and,
when labelled, ``label`` int32, with the label names in a ``comment label_names {json}`` header line, so
labels and their names travel inside the file (no side files); then, when the cloud records where its
points were seen from, ``view_x view_y view_z`` char (:attr:`PointCloud.view_dirs`). Foreign clouds (ASCII or double PLY,
PCD) are read through open3d by :func:`read_cloud`, which checks a PLY's body against its header first
(open3d reads what it can of a truncated file, warns and returns garbage) and drops non-finite points.
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

# PointCloud.view_dirs holds unit vectors times this, as int8: 3 bytes a point in memory, in files
# and on the bus, and the side a point was seen from needs no finer direction than 0.5 degrees.
VIEW_DIR_SCALE = 127


def quantise_view_dirs(mean_unit: np.ndarray) -> np.ndarray:
    """int8 (N, 3) ``view_dirs`` of float (N, 3) means of unit vectors (each of length <= 1)."""
    v = np.clip(np.asarray(mean_unit, np.float64), -1.0, 1.0) * VIEW_DIR_SCALE
    return np.rint(v).astype(np.int8)


def view_dirs_unit(view_dirs: np.ndarray) -> np.ndarray:
    """float32 (N, 3) mean unit vectors of int8 ``view_dirs``."""
    return np.asarray(view_dirs, np.float32) * np.float32(1.0 / VIEW_DIR_SCALE)


def rotate_view_dirs(view_dirs: np.ndarray | None, rotation: np.ndarray) -> np.ndarray | None:
    """int8 ``view_dirs`` turned by the (3, 3) ``rotation`` (requantised) as the cloud's points turn;
    a shift or a positive scale leaves them as they are. None stays None."""
    if view_dirs is None:
        return None
    return quantise_view_dirs(view_dirs_unit(view_dirs).astype(np.float64) @ np.asarray(rotation, np.float64).T)


class CloudError(Exception):
    """Base of every error about a point cloud or a cloud file."""


class CloudFormatError(CloudError, ValueError):
    """A cloud's arrays have the wrong shape or dtype, or a cloud file cannot be read.

    Also a ``ValueError``: a malformed cloud is the sender's bad input."""


class EmptyCloudError(CloudError, ValueError):
    """The cloud has no points, so there is nothing to render, map or store.

    Also a ``ValueError``: a map with no points is bad input, so the bus answers ``bad_request``
    (naming the map) rather than ``internal``."""


@dataclass
class PointCloud:
    """Points in world metres (z up) with colours and optional semantic labels.

    ``xyz`` float32 (N, 3); ``rgb`` uint8 (N, 3); ``labels`` int32 (N,) or None (-1 = unknown);
    ``label_names`` maps label ids to class names (room floors are named like ``"kitchen floor"``).

    ``view_dirs`` int8 (N, 3) or None: where each point was seen from, the mean of the unit vectors
    from the point towards the cameras whose observations were fused into it, times
    :data:`VIEW_DIR_SCALE` (its length, 0-127, says how much those directions agree). A surface's
    points thus record which of its two sides the robot saw; the renderer draws a point seen from
    one side only as unseen when a view looks at its other side (the neighbouring room's face of a
    wall is not this room's). None: not known (a foreign cloud, an older map).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    labels: np.ndarray | None = None
    label_names: dict[int, str] = field(default_factory=dict)
    view_dirs: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float32)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise CloudFormatError(f"xyz must be (N, 3), got {self.xyz.shape}")
        rgb = np.asarray(self.rgb)
        if rgb.dtype != np.uint8:
            # Colours in [0, 1] (open3d) are scaled; anything else must already be 0-255.
            rgb = np.clip(rgb * 255.0 if rgb.size and rgb.max() <= 1.0 else rgb, 0, 255)
            rgb = np.rint(rgb).astype(np.uint8)
        self.rgb = np.ascontiguousarray(rgb)
        if self.rgb.shape != self.xyz.shape:
            raise CloudFormatError(f"rgb shape {self.rgb.shape} != xyz shape {self.xyz.shape}")
        if self.labels is not None:
            self.labels = np.ascontiguousarray(self.labels, dtype=np.int32)
            if self.labels.shape != (len(self.xyz),):
                raise CloudFormatError(f"labels shape {self.labels.shape} != ({len(self.xyz)},)")
        if self.view_dirs is not None:
            vd = np.asarray(self.view_dirs)
            if vd.dtype != np.int8:
                raise CloudFormatError(f"view_dirs must be int8 (unit vectors x {VIEW_DIR_SCALE}), got {vd.dtype}")
            self.view_dirs = np.ascontiguousarray(vd)
            if self.view_dirs.shape != self.xyz.shape:
                raise CloudFormatError(f"view_dirs shape {self.view_dirs.shape} != xyz shape {self.xyz.shape}")
        if not np.isfinite(self.xyz).all():
            raise CloudFormatError("xyz contains non-finite values")

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def has_labels(self) -> bool:
        return self.labels is not None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if len(self) == 0:
            raise EmptyCloudError("an empty cloud has no bounds")
        return self.xyz.min(axis=0), self.xyz.max(axis=0)

    @property
    def has_view_dirs(self) -> bool:
        return self.view_dirs is not None

    def subset(self, index: np.ndarray) -> PointCloud:
        labels = None if self.labels is None else self.labels[index]
        views = None if self.view_dirs is None else self.view_dirs[index]
        return PointCloud(self.xyz[index], self.rgb[index], labels, dict(self.label_names), views)

    @classmethod
    def concatenate(cls, clouds: Sequence[PointCloud]) -> PointCloud:
        """Merge clouds; labels and view directions survive only if every part has them."""
        if not clouds:
            raise EmptyCloudError("nothing to concatenate")
        labelled = all(c.labels is not None for c in clouds)
        viewed = all(c.view_dirs is not None for c in clouds)
        names: dict[int, str] = {}
        for c in clouds:
            names.update(c.label_names)
        return cls(
            np.concatenate([c.xyz for c in clouds]),
            np.concatenate([c.rgb for c in clouds]),
            np.concatenate([c.labels for c in clouds]) if labelled else None,
            names,
            np.concatenate([c.view_dirs for c in clouds]) if viewed else None,
        )

    @classmethod
    def from_chunks(cls, chunks: Iterable, label_names: dict[int, str] | None = None) -> PointCloud:
        """Assemble a cloud from ``shared.schemas.MapChunk`` messages (any order)."""
        parts = sorted(chunks, key=lambda c: c.index)
        if not parts:
            raise EmptyCloudError("no chunks")
        if not any(len(c.xyz_m) for c in parts):
            first = parts[0]
            raise EmptyCloudError(f"map {first.map_id!r} version {first.version} has no points")
        labelled = all(c.labels is not None for c in parts)
        viewed = all(c.view_dirs is not None for c in parts)
        return cls(
            np.concatenate([c.xyz_m for c in parts]),
            np.concatenate([c.rgb for c in parts]),
            np.concatenate([c.labels for c in parts]) if labelled else None,
            dict(label_names or {}),
            np.concatenate([c.view_dirs for c in parts]) if viewed else None,
        )

    # --- files -------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write the cloud in the project's PLY layout (labels and their names inside the file)."""
        path = Path(path)
        try:
            with open(path, "wb") as fh:
                fh.write(header(len(self), self.labels is not None, self.label_names,
                                with_views=self.view_dirs is not None))
                # A slice at a time: storing a large cloud costs no second copy of it.
                for lo in range(0, len(self), _SLICE_POINTS):
                    hi = lo + _SLICE_POINTS
                    fh.write(records(self.xyz[lo:hi], self.rgb[lo:hi],
                                     None if self.labels is None else self.labels[lo:hi],
                                     view_dirs=None if self.view_dirs is None else self.view_dirs[lo:hi]))
        except OSError as exc:
            raise CloudFormatError(f"could not write {path}: {exc}") from exc

    @classmethod
    def load(cls, path: str | Path) -> PointCloud:
        """Read a cloud file: our PLY layout with its labels, or any PLY/PCD open3d reads."""
        return read_cloud(path)


def sample_mesh(vertices: np.ndarray, triangles: np.ndarray, vertex_colors: np.ndarray,
                triangle_labels: np.ndarray | None = None, *, n_points: int, seed: int = 0, texture=None,
                label_names: dict[int, str] | None = None, stratified: bool = False) -> PointCloud:
    """``n_points`` samples spread uniformly by area over a triangle mesh, with interpolated colours
    (or the texel under the sample) and their triangle's label - a cloud with no pose, scale or depth
    error: the paper's "human-curated" cloud, and the ground truth of renderer tests.

    Independent random samples (the default) clump and leave gaps several times their mean spacing
    wide. ``stratified`` spreads them evenly instead: each triangle gets its area's share of the
    samples by systematic rounding (the total stays ``n_points``), placed on a randomly shifted
    rank-1 lattice of the unit square (the golden-ratio Kronecker sequence; a Cranley-Patterson
    rotation per triangle) mapped onto the triangle by the same area-preserving square-root warp.
    That is blue-noise-like at the cost of random sampling, as a scanned dataset's points are: no
    gap much wider than the spacing, so the renderer's footprints, sized from the spacing, close.

    Args:
        vertices: (V, 3) positions; triangles: (T, 3) vertex indices; vertex_colors: (V, 3) in [0, 1].
        triangle_labels: (T,) label per triangle (-1: unknown); None: the cloud has no labels.
        texture: optional ``libs.world.scene.Texture`` (per-triangle material and UVs).
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise CloudFormatError(f"need (V, 3) vertices and (T, 3) triangles, got {v.shape} and {t.shape}")
    if n_points < 1:
        raise CloudFormatError("n_points must be positive")
    corners = v[t]  # (T, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    total = float(area.sum())
    if total <= 0:
        raise CloudFormatError("the mesh has no surface area")
    rng = np.random.default_rng(seed)
    if stratified:
        tri, a, b = _stratified_samples(area / total, n_points, rng)
    else:
        tri = rng.choice(len(t), size=n_points, p=area / total)
        a, b = rng.random(n_points), rng.random(n_points)
    # Uniform barycentrics by the square-root trick (Osada et al. 2002).
    r1, r2 = np.sqrt(a), b
    bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    xyz = np.einsum("nk,nkd->nd", bary, corners[tri])
    rgb = np.einsum("nk,nkd->nd", bary, np.asarray(vertex_colors, np.float64)[t[tri]])
    if texture is not None:
        mids = np.asarray(texture.material_ids)[tri]
        for m in np.unique(mids[mids >= 0]):
            sel = np.flatnonzero(mids == m)
            img = texture.images[int(m)]
            uv = np.einsum("nk,nkd->nd", bary[sel], np.asarray(texture.triangle_uvs, np.float64)[tri[sel]])
            h, w = img.shape[:2]
            # Texture v runs upwards, image rows downwards.
            px = np.clip((uv[:, 0] % 1.0) * w, 0, w - 1).astype(np.int64)
            py = np.clip((1.0 - uv[:, 1] % 1.0) * h, 0, h - 1).astype(np.int64)
            rgb[sel] = img[py, px, :3] / 255.0
    labels = None if triangle_labels is None else np.asarray(triangle_labels, np.int32)[tri]
    return PointCloud(xyz.astype(np.float32), np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8), labels,
                      dict(label_names or {}))




# The golden ratio's fractional part: the Kronecker sequence frac(i * g) of the stratified sampling
# spreads any number of points evenly over [0, 1) (three-gap theorem: at most three gap lengths).
_GOLDEN_FRACTION = (math.sqrt(5.0) - 1.0) / 2.0


def _stratified_samples(share: np.ndarray, n_points: int, rng: np.random.Generator):
    """(triangle of each sample, a, b in [0, 1)): ``n_points`` samples, triangle t getting
    ``share[t] * n_points`` of them by systematic rounding, each triangle's on the lattice
    ((i + u) / n_t, frac(i g + v)) with its own random shift (u, v)."""
    edges = np.minimum(np.floor(np.cumsum(share) * n_points + rng.random()), n_points)
    edges[-1] = n_points  # floor(n + u) with u < 1, but for the cumulative sum's rounding
    counts = np.diff(np.concatenate([[0.0], edges])).astype(np.int64)
    tri = np.repeat(np.arange(len(share)), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    i = np.arange(len(tri)) - np.repeat(first, counts)
    shift = rng.random((len(share), 2))
    n_t = counts[tri]
    a = (i + shift[tri, 0]) / n_t
    b = (i * _GOLDEN_FRACTION + shift[tri, 1]) % 1.0
    return tri, a, b


# --- the PLY layout ------------------------------------------------------------------------------

_BASE = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
# PointCloud.view_dirs, after the label when there is one: char (int8) unit vectors x VIEW_DIR_SCALE.
_VIEWS = [("view_x", "i1"), ("view_y", "i1"), ("view_z", "i1")]
_LABEL_COMMENT = "label_names "
_PLY_TYPES = {"f4": "float", "u1": "uchar", "i4": "int", "i1": "char"}


def vertex_dtype(with_labels: bool, with_views: bool = False) -> np.dtype:
    return np.dtype(_BASE + ([("label", "<i4")] if with_labels else []) + (_VIEWS if with_views else []))


def _our_properties(with_labels: bool, with_views: bool = False) -> list[list[str]]:
    dt = vertex_dtype(with_labels, with_views)
    return [[_PLY_TYPES[dt.fields[n][0].str[1:]], n] for n in dt.names]


def header(point_count: int, with_labels: bool, label_names: dict[int, str] | None = None,
           comment: str = "", with_views: bool = False) -> bytes:
    """The PLY header for ``point_count`` records (the gateway streams a map as header + records)."""
    lines = ["ply", "format binary_little_endian 1.0"]
    if comment:
        lines.append(f"comment {comment}")
    if with_labels and label_names:
        names = {str(k): v for k, v in sorted(label_names.items())}
        lines.append("comment " + _LABEL_COMMENT + json.dumps(names, separators=(",", ":")))
    lines += [f"element vertex {point_count}"] + [f"property {t} {n}"
                                                  for t, n in _our_properties(with_labels, with_views)]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def records(xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None = None,
            with_labels: bool | None = None, view_dirs: np.ndarray | None = None) -> bytes:
    """Packed vertex records (one vectorised copy); ``with_labels`` without labels writes -1."""
    with_labels = labels is not None if with_labels is None else with_labels
    out = np.empty(len(xyz), vertex_dtype(with_labels, view_dirs is not None))
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    out["red"], out["green"], out["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if with_labels:
        out["label"] = labels if labels is not None else -1
    if view_dirs is not None:
        for i, (name, _) in enumerate(_VIEWS):
            out[name] = view_dirs[:, i]
    return out.tobytes()


def encode(cloud: PointCloud, with_labels: bool = True, comment: str = "") -> bytes:
    """The whole cloud as a PLY file in our layout (``with_labels=False`` drops the labels)."""
    labels = cloud.labels if with_labels else None
    names = cloud.label_names if labels is not None else None
    views = cloud.view_dirs
    return (header(len(cloud), labels is not None, names, comment, with_views=views is not None)
            + records(cloud.xyz, cloud.rgb, labels, view_dirs=views))


@dataclass(frozen=True)
class _Layout:
    """What the header of a PLY in our layout says: records, labels, label names, where the body starts."""

    count: int
    with_labels: bool
    names: dict[int, str]
    body_offset: int
    with_views: bool = False

    @property
    def dtype(self) -> np.dtype:
        return vertex_dtype(self.with_labels, self.with_views)


def _our_layout(head: bytes) -> _Layout | None:
    """The layout of a PLY of ours from its first bytes (header included); None for any other file."""
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        return None
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        return None
    props = [ln.split()[1:] for ln in lines if ln.startswith("property ")]
    count = next((int(ln.split()[2]) for ln in lines if ln.startswith("element vertex ")), None)
    elements = [ln for ln in lines if ln.startswith("element ")]
    layouts = [(lab, views) for lab in (True, False) for views in (False, True)
               if props == _our_properties(lab, views)]
    if count is None or len(elements) != 1 or not layouts:
        return None
    with_labels, with_views = layouts[0]
    names: dict[int, str] = {}
    for ln in lines:
        if ln.startswith("comment " + _LABEL_COMMENT):
            try:
                raw = json.loads(ln[len("comment " + _LABEL_COMMENT):])
                names = {int(k): str(v) for k, v in raw.items()}
            except (ValueError, AttributeError) as exc:
                raise CloudFormatError(f"unreadable label names in the PLY header: {exc}") from None
    return _Layout(count, with_labels, names, end + len(b"end_header\n"), with_views)


def _check_body(layout: _Layout, body_bytes: int) -> None:
    need = layout.count * layout.dtype.itemsize
    if body_bytes < need:
        raise CloudFormatError(f"PLY body holds {body_bytes} bytes, {layout.count} vertices need {need}")


def _unpack(rec: np.ndarray, xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None,
            views: np.ndarray | None = None) -> np.ndarray:
    """Records into the columns ``xyz``/``rgb``/``labels``/``views`` (same length); returns which rows
    are finite."""
    for i, axis in enumerate("xyz"):
        xyz[:, i] = rec[axis]
    for i, channel in enumerate(("red", "green", "blue")):
        rgb[:, i] = rec[channel]
    if labels is not None:
        labels[:] = rec["label"]
    if views is not None:
        for i, (name, _) in enumerate(_VIEWS):
            views[:, i] = rec[name]
    return np.isfinite(xyz).all(axis=1)


def _assemble(layout: _Layout, fill) -> PointCloud:
    """A cloud of ``layout.count`` points; ``fill(xyz, rgb, labels)`` writes the columns and returns the
    finite-row mask. The columns are allocated once: no second copy of the records."""
    xyz = np.empty((layout.count, 3), np.float32)
    rgb = np.empty((layout.count, 3), np.uint8)
    labels = np.empty(layout.count, np.int32) if layout.with_labels else None
    views = np.empty((layout.count, 3), np.int8) if layout.with_views else None
    finite = fill(xyz, rgb, labels, views)
    if not finite.all():
        if not finite.any():
            raise CloudFormatError("every point is non-finite")
        log.warning("dropping %d non-finite points", int((~finite).sum()))
        xyz, rgb = xyz[finite], rgb[finite]
        labels = None if labels is None else labels[finite]
        views = None if views is None else views[finite]
    return PointCloud(xyz, rgb, labels, layout.names, views)


def decode(data: bytes) -> PointCloud | None:
    """The cloud in a PLY of our layout; None for any other PLY (left to :func:`read_cloud`).

    Raises :class:`CloudFormatError` when the file is ours but its body is cut short."""
    layout = _our_layout(data)
    if layout is None:
        return None
    body = memoryview(data)[layout.body_offset:]
    _check_body(layout, len(body))
    rec = np.frombuffer(body, layout.dtype, layout.count)
    return _assemble(layout, lambda xyz, rgb, labels, views: _unpack(rec, xyz, rgb, labels, views))


_HEAD_BYTES = 1 << 20  # a header longer than this (label names of a huge label set?) is read by open3d
_SLICE_POINTS = 1 << 20  # records read or written at a time when a file is streamed


def record_chunks(fh, dtype: np.dtype, count: int, chunk: int = _SLICE_POINTS, what: str = "PLY body"):
    """``(first index, records)`` for ``count`` fixed-size records read from ``fh``'s position ``chunk``
    at a time (a streamed file is never whole in memory); a body that ends early is a
    :class:`CloudFormatError`, not a short cloud."""
    for lo in range(0, count, chunk):
        want = min(chunk, count - lo)
        rec = np.fromfile(fh, dtype, want)
        if len(rec) != want:
            raise CloudFormatError(f"{what} ends after {lo + len(rec)} of {count} records")
        yield lo, rec


def _read_ours(path: Path) -> PointCloud | None:
    """:func:`decode` straight from a file, a slice of records at a time (the file is never in memory
    whole: what is held is the cloud itself)."""
    with open(path, "rb") as fh:
        layout = _our_layout(fh.read(_HEAD_BYTES))
        if layout is None:
            return None
        _check_body(layout, path.stat().st_size - layout.body_offset)

        def fill(xyz, rgb, labels, views):
            fh.seek(layout.body_offset)
            finite = np.empty(layout.count, bool)
            for lo, rec in record_chunks(fh, layout.dtype, layout.count):
                hi = lo + len(rec)
                finite[lo:hi] = _unpack(rec, xyz[lo:hi], rgb[lo:hi], None if labels is None else labels[lo:hi],
                                        None if views is None else views[lo:hi])
            return finite

        return _assemble(layout, fill)


@dataclass(frozen=True)
class CopiedCloud:
    """What :func:`copy_ours` wrote: the finite points' count and bounds, and the file's labels."""

    count: int
    bounds_min: tuple[float, float, float]
    bounds_max: tuple[float, float, float]
    with_labels: bool
    label_names: dict[int, str]


def copy_ours(src: str | Path, dst: str | Path) -> CopiedCloud | None:
    """Copy a PLY of our layout from ``src`` to ``dst`` a slice of records at a time, dropping
    non-finite points: what an upload of any size costs in memory is one slice (~16 MB), not the cloud.
    None when ``src`` is not in our layout (the caller parses it whole); :class:`CloudFormatError` when
    it is ours but cut short, or holds no finite point.

    Two passes (count and bounds first, since the header states the count; then the records), both
    read sequentially from a file the page cache holds."""
    src = Path(src)
    with open(src, "rb") as fh:
        layout = _our_layout(fh.read(_HEAD_BYTES))
        if layout is None:
            return None
        _check_body(layout, src.stat().st_size - layout.body_offset)

        def slices():
            fh.seek(layout.body_offset)
            for _lo, rec in record_chunks(fh, layout.dtype, layout.count):
                xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
                finite = np.isfinite(xyz).all(axis=1)
                yield rec, xyz, finite

        count, lo_b, hi_b = 0, np.full(3, np.inf), np.full(3, -np.inf)
        for _rec, xyz, finite in slices():
            n = int(finite.sum())
            if n:
                count += n
                lo_b = np.minimum(lo_b, xyz[finite].min(axis=0))
                hi_b = np.maximum(hi_b, xyz[finite].max(axis=0))
        if not count:
            raise CloudFormatError("every point is non-finite" if layout.count else "no points")
        if count < layout.count:
            log.warning("dropping %d non-finite points", layout.count - count)
        with open(dst, "wb") as out:
            out.write(header(count, layout.with_labels, layout.names, with_views=layout.with_views))
            for rec, _xyz, finite in slices():
                out.write((rec if finite.all() else rec[finite]).tobytes())
    return CopiedCloud(count, tuple(float(v) for v in lo_b), tuple(float(v) for v in hi_b),
                       layout.with_labels, dict(layout.names))


def read_cloud(path: str | Path) -> PointCloud:
    """A cloud file as a :class:`PointCloud`: our layout (labels kept), or any PLY/PCD open3d reads.

    Every way a file can be unreadable (missing, truncated, malformed header, no points, every point
    non-finite) is a :class:`CloudFormatError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise CloudFormatError(f"no such cloud file: {path}")
    try:
        if path.suffix.lower() == ".ply":
            ours = _read_ours(path)
            if ours is not None:
                return ours
            _check_ply_file(path)
        return _read_foreign(path)
    except CloudFormatError as exc:
        raise CloudFormatError(f"{path.name}: {exc}") from None


def read_cloud_bytes(data: bytes, filename: str) -> PointCloud:
    """:func:`read_cloud` for an upload's bytes; ``filename``'s suffix (.ply or .pcd) names the format."""
    suffix = Path(filename).suffix.lower()
    if suffix not in (".ply", ".pcd"):
        raise CloudFormatError(f"{filename!r}: only .ply and .pcd clouds can be read")
    if suffix == ".ply":
        try:
            ours = decode(bytes(data))
        except CloudFormatError as exc:
            raise CloudFormatError(f"{filename}: {exc}") from None
        if ours is not None:
            return ours
    # open3d reads only from a path.
    with tempfile.TemporaryDirectory(prefix="cloud-") as tmp:
        p = Path(tmp) / f"upload{suffix}"
        p.write_bytes(bytes(data))
        try:
            return read_cloud(p)
        except CloudFormatError as exc:
            raise CloudFormatError(str(exc).replace(p.name, filename, 1)) from None


def _read_foreign(path: Path) -> PointCloud:
    from shared.o3d import o3d

    pcd = o3d.io.read_point_cloud(str(path))
    xyz = np.asarray(pcd.points)
    if len(xyz) == 0:
        raise CloudFormatError("no points could be read (not a PLY/PCD point cloud?)")
    # Rows must stay finite as float32 (the cloud's storage type): huge doubles are garbage too.
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.isfinite(np.asarray(xyz, np.float32)).all(axis=1)
    if not finite.any():
        raise CloudFormatError("every point is non-finite")
    rgb = np.asarray(pcd.colors) if pcd.has_colors() else np.full((len(xyz), 3), 0.5)
    if not finite.all():
        log.warning("%s: dropping %d non-finite points", path.name, int((~finite).sum()))
    return PointCloud(xyz[finite], rgb[finite])


_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_ply_file(path: Path) -> None:
    """Raise :class:`CloudFormatError` when a PLY's header is unreadable or its vertices are cut short.

    Binary files: the bytes after the header must hold every element up to the vertices (fixed-size
    records only; a list property before them stops the check). ASCII: one line per record. The file
    is read from disk as it is checked, never into memory whole."""
    with open(path, "rb") as fh:
        data = fh.read(_HEAD_BYTES)
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise CloudFormatError("not a PLY file (no 'ply' magic or no end_header)")
    nl = data.find(b"\n", end)
    body_offset = nl + 1 if nl >= 0 else path.stat().st_size
    body_bytes = path.stat().st_size - body_offset
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ")), "")
    elements: list[list] = []  # [name, count, record size or None for lists]
    try:
        for ln in lines:
            parts = ln.split()
            if parts[:1] == ["element"]:
                elements.append([parts[1], int(parts[2]), 0])
            elif parts[:1] == ["property"] and elements:
                size = None if parts[1] == "list" else _PLY_SIZES.get(parts[1])
                elements[-1][2] = None if size is None or elements[-1][2] is None else elements[-1][2] + size
    except (IndexError, ValueError):
        raise CloudFormatError("malformed PLY header") from None
    if not any(e[0] == "vertex" for e in elements):
        raise CloudFormatError("the PLY has no vertex element")
    if fmt == "ascii":
        need = 0
        for el, count, _ in elements:
            need += count
            if el == "vertex":
                break
        with open(path, "rb") as fh:
            fh.seek(body_offset)
            have = sum(1 for ln in fh if ln.strip())
        if have < need:
            raise CloudFormatError(f"truncated PLY ({have} records, the header announces {need})")
        return
    need = 0
    for el, count, size in elements:
        if size is None:
            return  # variable-length records before the vertices: leave it to the reader
        need += count * size
        if el == "vertex":
            break
    if body_bytes < need:
        raise CloudFormatError(f"truncated PLY (body holds {body_bytes} bytes, the vertices need {need})")
