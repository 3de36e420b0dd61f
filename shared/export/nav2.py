"""A Nav2 (ROS 2 ``nav2_map_server``) map from a point cloud: occupancy grid, PGM image, YAML.

The map_server format is a pair of files. The YAML names the image and says how to read it:
``resolution`` (metres per pixel), ``origin`` (x, y, yaw of the *lower-left* pixel in the map frame),
``negate``, ``occupied_thresh``, ``free_thresh`` and ``mode``. In ``trinary`` mode with ``negate: 0`` a
pixel value v reads as the occupancy p = (255 - v) / 255: occupied when p > occupied_thresh, free when
p < free_thresh, unknown otherwise. We write what ``map_saver`` writes: 0 occupied, 254 free, 205
unknown, with thresholds 0.65 / 0.196 (205 gives p = 0.19608, just above 0.196: unknown).

Our world frame is REP-103 (x forward, y left, z up), so the map frame needs no rotation: yaw 0. Image
row 0 is the largest y (the top of the picture), as every image viewer and map_server expect.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

# Cell values of the ROS OccupancyGrid message (nav_msgs/OccupancyGrid.data).
UNKNOWN, FREE, OCCUPIED = -1, 0, 100

PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


class OccupancyConfig(BaseModel):
    """How a cloud becomes a 2D grid: points within ``floor_band_m`` of the floor mark free cells, points
    in ``obstacle_band_m`` above it (the robot's body height) mark occupied ones; occupied wins."""

    model_config = ConfigDict(extra="forbid")

    cell_m: float = Field(0.05, ge=0.01, le=1.0)
    floor_band_m: tuple[float, float] = (-0.15, 0.15)
    obstacle_band_m: tuple[float, float] = (0.20, 1.60)
    min_obstacle_points: int = Field(3, ge=1)
    min_floor_points: int = Field(1, ge=1)
    margin_m: float = Field(0.5, ge=0.0, le=10.0)
    max_cells: int = Field(25_000_000, ge=1, description="refuse grids larger than this (a 250 m x 250 m floor)")

    @model_validator(mode="after")
    def _bands(self):
        for name in ("floor_band_m", "obstacle_band_m"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"{name} must be two finite numbers, low < high; got {(lo, hi)}")
        return self


@dataclass(frozen=True)
class Nav2Map:
    """``cells[row, col]`` of UNKNOWN / FREE / OCCUPIED; row 0 is the top (largest y) of the map.

    ``origin_m`` is the world (x, y) of the lower-left corner of the lower-left cell, as in the YAML.
    """

    cells: np.ndarray  # int8 (rows, cols)
    origin_m: tuple[float, float]
    resolution_m: float
    floor_z_m: float

    def cell_of(self, xy) -> np.ndarray:
        """(N, 2) world xy -> (N, 2) integer (row, col); may fall outside the grid."""
        xy = np.atleast_2d(np.asarray(xy, float))
        rows = self.cells.shape[0]
        col = np.floor((xy[:, 0] - self.origin_m[0]) / self.resolution_m)
        row = rows - 1 - np.floor((xy[:, 1] - self.origin_m[1]) / self.resolution_m)
        return np.stack([row, col], axis=1).astype(np.int64)

    def pgm(self) -> bytes:
        """The grid as a binary (P5) 8-bit PGM in map_saver's trinary values."""
        img = np.full(self.cells.shape, PGM_UNKNOWN, np.uint8)
        img[self.cells == FREE] = PGM_FREE
        img[self.cells == OCCUPIED] = PGM_OCCUPIED
        rows, cols = img.shape
        return f"P5\n# SpatialAnt map, floor z {self.floor_z_m:.3f} m\n{cols} {rows}\n255\n".encode("ascii") + img.tobytes()

    def yaml(self, image_name: str) -> str:
        """The map_server YAML for the PGM saved as ``image_name`` (relative to the YAML's folder)."""
        if not image_name or "\n" in image_name or ":" in image_name:
            raise ValueError(f"bad image name {image_name!r}")
        x0, y0 = self.origin_m
        return (f"image: {image_name}\n"
                "mode: trinary\n"
                f"resolution: {self.resolution_m:.6g}\n"
                f"origin: [{x0:.6f}, {y0:.6f}, 0.0]\n"
                "negate: 0\n"
                f"occupied_thresh: {OCCUPIED_THRESH}\n"
                f"free_thresh: {FREE_THRESH}\n")


class EmptyMapError(ValueError):
    """The cloud has no points to build an occupancy grid from."""


def floor_z_of(xyz: np.ndarray, bin_m: float = 0.05) -> float:
    """The lowest well-populated height: the floor of the lowest storey.

    The minimum z alone is one stray point below the floor; the mode of the lowest 20 % of heights is
    the floor slab, which holds far more points than any outlier.
    """
    z = np.asarray(xyz, np.float64)[:, 2]
    if not len(z):
        raise EmptyMapError("no points")
    low = z[z <= np.quantile(z, 0.2)]
    edges = np.arange(low.min(), low.max() + 2 * bin_m, bin_m)
    hist, edges = np.histogram(low, edges)
    i = int(np.argmax(hist))
    return float(0.5 * (edges[i] + edges[i + 1]))


def occupancy_from_cloud(xyz: np.ndarray, floor_z_m: float | None = None,
                         config: OccupancyConfig | None = None) -> Nav2Map:
    """The occupancy grid of the floor at ``floor_z_m`` (default: :func:`floor_z_of`) of a world z-up cloud."""
    cfg = config or OccupancyConfig()
    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not len(xyz):
        raise EmptyMapError(f"need an (N, 3) cloud with points, got shape {xyz.shape}")
    floor = floor_z_of(xyz) if floor_z_m is None else float(floor_z_m)
    if not math.isfinite(floor):
        raise ValueError(f"floor_z_m must be finite, got {floor_z_m}")
    dz = xyz[:, 2] - floor
    on_floor = (dz >= cfg.floor_band_m[0]) & (dz <= cfg.floor_band_m[1])
    obstacle = (dz >= cfg.obstacle_band_m[0]) & (dz <= cfg.obstacle_band_m[1])
    relevant = on_floor | obstacle
    xy = xyz[relevant, :2]
    extent = xy if len(xy) else xyz[:, :2]  # nothing at this height: the footprint, all unknown
    lo = extent.min(axis=0) - cfg.margin_m
    hi = extent.max(axis=0) + cfg.margin_m
    cols = max(1, int(math.ceil((hi[0] - lo[0]) / cfg.cell_m)))
    rows = max(1, int(math.ceil((hi[1] - lo[1]) / cfg.cell_m)))
    if rows * cols > cfg.max_cells:
        raise ValueError(f"a {rows} x {cols} grid exceeds max_cells={cfg.max_cells}; use a coarser cell_m")
    col = np.clip(np.floor((xy[:, 0] - lo[0]) / cfg.cell_m).astype(np.int64), 0, cols - 1)
    row_from_bottom = np.clip(np.floor((xy[:, 1] - lo[1]) / cfg.cell_m).astype(np.int64), 0, rows - 1)
    flat = (rows - 1 - row_from_bottom) * cols + col
    kinds = obstacle[relevant]
    n_obs = np.bincount(flat[kinds], minlength=rows * cols)
    n_floor = np.bincount(flat[~kinds], minlength=rows * cols)
    cells = np.full(rows * cols, UNKNOWN, np.int8)
    cells[n_floor >= cfg.min_floor_points] = FREE
    cells[n_obs >= cfg.min_obstacle_points] = OCCUPIED
    return Nav2Map(cells.reshape(rows, cols), (float(lo[0]), float(lo[1])), cfg.cell_m, floor)


def nav2_files(grid: Nav2Map, stem: str) -> dict[str, bytes]:
    """``{stem}.pgm`` and ``{stem}.yaml`` (the YAML names the PGM relative to itself)."""
    return {f"{stem}.pgm": grid.pgm(), f"{stem}.yaml": grid.yaml(f"{stem}.pgm").encode("utf-8")}
