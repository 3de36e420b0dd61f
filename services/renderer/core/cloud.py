"""Coloured, optionally labelled point clouds and their spatial index.

A map is rendered many times (every candidate of every navigation step), so everything that depends
only on the cloud is done once here: points are reordered into cubic blocks (``block_m`` on a side)
so that a view touches only the blocks its frustum and range reach, and each block keeps its tight
bounding box for the frustum test.
"""

from __future__ import annotations

import json
import logging

import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.renderer.core.errors import CloudFormatError, EmptyCloudError
from shared.geometry import PinholeCamera

log = logging.getLogger(__name__)


@dataclass
class PointCloud:
    """Points in world metres (z up) with colours and optional semantic labels.

    ``xyz`` float32 (N, 3); ``rgb`` uint8 (N, 3); ``labels`` int32 (N,) or None (-1 = unknown);
    ``label_names`` maps label ids to class names (room floors are named like ``"kitchen floor"``).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    labels: np.ndarray | None = None
    label_names: dict[int, str] = field(default_factory=dict)

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

    def subset(self, index: np.ndarray) -> PointCloud:
        labels = None if self.labels is None else self.labels[index]
        return PointCloud(self.xyz[index], self.rgb[index], labels, dict(self.label_names))

    @classmethod
    def concatenate(cls, clouds: Sequence[PointCloud]) -> PointCloud:
        """Merge clouds; labels survive only if every part has them."""
        if not clouds:
            raise EmptyCloudError("nothing to concatenate")
        labelled = all(c.labels is not None for c in clouds)
        names: dict[int, str] = {}
        for c in clouds:
            names.update(c.label_names)
        return cls(
            np.concatenate([c.xyz for c in clouds]),
            np.concatenate([c.rgb for c in clouds]),
            np.concatenate([c.labels for c in clouds]) if labelled else None,
            names,
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
        return cls(
            np.concatenate([c.xyz_m for c in parts]),
            np.concatenate([c.rgb for c in parts]),
            np.concatenate([c.labels for c in parts]) if labelled else None,
            dict(label_names or {}),
        )

    # --- files -------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write a PLY (open3d); labels and their names go to ``<stem>.labels.npz`` beside it."""
        import open3d as o3d

        path = Path(path)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.xyz.astype(np.float64)))
        pcd.colors = o3d.utility.Vector3dVector(self.rgb.astype(np.float64) / 255.0)
        if not o3d.io.write_point_cloud(str(path), pcd):
            raise CloudFormatError(f"could not write {path}")
        side = path.with_suffix(".labels.npz")
        if self.labels is not None:
            np.savez_compressed(
                side, labels=self.labels, names=json.dumps({str(k): v for k, v in self.label_names.items()})
            )
        elif side.exists():
            side.unlink()

    @classmethod
    def load(cls, path: str | Path) -> PointCloud:
        """Read a PLY/PCD (anything open3d reads) and its labels side file when present."""
        import open3d as o3d

        path = Path(path)
        if not path.is_file():
            raise CloudFormatError(f"no such cloud file: {path}")
        pcd = o3d.io.read_point_cloud(str(path))
        xyz = np.asarray(pcd.points, dtype=np.float32)
        rgb = (
            np.asarray(pcd.colors) if pcd.has_colors() else np.full((len(xyz), 3), 0.5)
        )
        labels, names = None, {}
        side = path.with_suffix(".labels.npz")
        if side.is_file():
            with np.load(side) as data:
                labels = data["labels"]
                names = {int(k): v for k, v in json.loads(str(data["names"])).items()}
        return cls(xyz, rgb, labels, names)


def sample_mesh(vertices: np.ndarray, triangles: np.ndarray, vertex_colors: np.ndarray,
                triangle_labels: np.ndarray | None = None, *, n_points: int, seed: int = 0, texture=None,
                label_names: dict[int, str] | None = None) -> PointCloud:
    """``n_points`` samples spread uniformly by area over a triangle mesh, with interpolated colours
    (or the texel under the sample) and their triangle's label - a cloud with no pose, scale or depth
    error: the paper's "human-curated" cloud, and the ground truth of renderer tests.

    Args:
        vertices: (V, 3) positions; triangles: (T, 3) vertex indices; vertex_colors: (V, 3) in [0, 1].
        triangle_labels: (T,) label per triangle (-1: unknown); None: the cloud has no labels.
        texture: optional ``services.robot_io.core.scene.Texture`` (per-triangle material and UVs).
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
    tri = rng.choice(len(t), size=n_points, p=area / total)
    # Uniform barycentrics by the square-root trick (Osada et al. 2002).
    r1, r2 = np.sqrt(rng.random(n_points)), rng.random(n_points)
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


@dataclass(frozen=True)
class Frustum:
    """Half-spaces ``n . p_cam + d <= 0`` that together contain every point that can reach a pixel."""

    normals: np.ndarray  # (P, 3) in the camera frame
    offsets: np.ndarray  # (P,)

    @classmethod
    def for_camera(
        cls, camera: PinholeCamera, near_m: float, far_m: float, margin_px: float = 2.0
    ) -> Frustum:
        # A point splats into pixels up to one away from the one it rounds to, so the frustum is
        # widened by the splat radius plus slack for rounding.
        w, h = camera.width_px, camera.height_px
        x_lo = (-0.5 - margin_px - camera.cx) / camera.fx
        x_hi = (w - 0.5 + margin_px - camera.cx) / camera.fx
        y_lo = (-0.5 - margin_px - camera.cy) / camera.fy
        y_hi = (h - 0.5 + margin_px - camera.cy) / camera.fy
        normals = np.array(
            [[1.0, 0.0, -x_hi], [-1.0, 0.0, x_lo], [0.0, 1.0, -y_hi], [0.0, -1.0, y_lo],
             [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]
        )
        offsets = np.array([0.0, 0.0, 0.0, 0.0, near_m, -far_m])
        return cls(normals, offsets)


_CORNERS = np.array(
    [[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64
)


class IndexedCloud:
    """A cloud reordered into spatial blocks, built once per map and shared by every view.

    ``cloud`` is the reordered cloud; block ``b`` holds ``cloud[starts[b]:starts[b] + counts[b]]``
    whose tight bounds are ``block_min[b]``, ``block_max[b]``. ``uid`` identifies this build (a
    new map version gets a new one) and keys every cache derived from it; ``cache`` holds such
    derived data (device tensors, top-down grids) so that it lives and dies with the map.
    """

    def __init__(self, cloud: PointCloud, block_m: float = 1.0, area_cell_m: float = 0.05, seed: int = 0):
        if len(cloud) == 0:
            raise EmptyCloudError("cannot index an empty cloud")
        if not block_m > 0:
            raise ValueError(f"block_m must be positive, got {block_m}")
        self.block_m = float(block_m)
        self.uid = uuid.uuid4().hex
        self.cache: dict = {}
        lo = cloud.xyz.min(axis=0)
        cells = np.floor((cloud.xyz - lo) / self.block_m).astype(np.int64)
        dims = cells.max(axis=0) + 1
        key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        # Points are shuffled inside their block, so any prefix of a block is a uniform subsample:
        # level of detail then costs nothing but a shorter slice.
        shuffle = np.random.default_rng(seed).permutation(len(key))
        order = shuffle[np.argsort(key[shuffle], kind="stable")]
        self.cloud = cloud.subset(order)
        key = key[order]
        boundaries = np.flatnonzero(np.diff(key)) + 1
        self.starts = np.concatenate([[0], boundaries]).astype(np.int64)
        self.counts = np.diff(np.concatenate([self.starts, [len(key)]])).astype(np.int64)
        self.block_min = np.minimum.reduceat(self.cloud.xyz, self.starts, axis=0).astype(np.float64)
        self.block_max = np.maximum.reduceat(self.cloud.xyz, self.starts, axis=0).astype(np.float64)
        # Surface area per block, from the number of occupied area_cell_m voxels: what level of
        # detail needs to know how many pixels a block can cover.
        fine = np.floor((self.cloud.xyz - lo) / area_cell_m).astype(np.int64)
        fdims = fine.max(axis=0) + 1
        fkey = (fine[:, 0] * fdims[1] + fine[:, 1]) * fdims[2] + fine[:, 2]
        block_of = np.repeat(np.arange(len(self.starts)), self.counts)
        occupied = np.unique(block_of.astype(np.int64) * int(fdims.prod()) + fkey) // int(fdims.prod())
        self.block_area_m2 = np.bincount(occupied, minlength=len(self.starts)) * area_cell_m**2
        log.debug("indexed %d points into %d blocks of %.2f m", len(cloud), len(self.starts), block_m)

    def __len__(self) -> int:
        return len(self.cloud)

    @property
    def block_count(self) -> int:
        return len(self.starts)

    def visible_blocks(self, world_from_camera: np.ndarray, frustum: Frustum) -> np.ndarray:
        """Boolean mask of blocks that may hold a point inside ``frustum`` (conservative)."""
        ext = self.block_max - self.block_min
        corners = self.block_min[:, None, :] + _CORNERS[None, :, :] * ext[:, None, :]  # (B, 8, 3)
        r = world_from_camera[:3, :3]
        t = world_from_camera[:3, 3]
        cam = (corners - t) @ r  # (B, 8, 3) in the camera frame
        dist = cam @ frustum.normals.T + frustum.offsets  # (B, 8, P)
        outside = (dist > 0).all(axis=1).any(axis=1)
        return ~outside

    def lod_counts(self, world_from_camera: np.ndarray, focal_px: float, points_per_px: float) -> np.ndarray:
        """Points to keep per block so that a block yields about ``points_per_px`` points per pixel
        it can cover: its surface area seen face-on from its nearest point (an upper bound, so
        grazing surfaces keep more than they need, never fewer)."""
        cam = world_from_camera[:3, 3]
        gap = np.maximum(np.maximum(self.block_min - cam, cam - self.block_max), 0.0)
        dist = np.maximum(np.linalg.norm(gap, axis=1), 1e-3)
        pixels = self.block_area_m2 * (focal_px / dist) ** 2
        return np.minimum(self.counts, np.ceil(points_per_px * pixels).astype(np.int64))

    def point_indices(
        self, block_mask: np.ndarray | None = None, counts: np.ndarray | None = None
    ) -> np.ndarray:
        """Indices (into ``cloud``) of the points of the selected blocks, int64, ascending;
        with ``counts``, only the first ``counts[b]`` points of block ``b`` (a uniform subsample)."""
        if block_mask is None and counts is None:
            return np.arange(len(self.cloud), dtype=np.int64)
        if block_mask is None:
            block_mask = np.ones(len(self.starts), bool)
        starts = self.starts[block_mask]
        counts = (self.counts if counts is None else counts)[block_mask]
        total = int(counts.sum())
        if total == 0:
            return np.empty(0, dtype=np.int64)
        # Runs of consecutive ids: offset each run's arange by its start.
        shift = starts - (np.cumsum(counts) - counts)
        return np.repeat(shift, counts) + np.arange(total, dtype=np.int64)


