"""2D occupancy per floor, rebuilt from the exploration's free-space scans.

Each scan holds, per direction, the range of the first obstacle in the body band (``inf``: none
within sensor range, ``nan``: not seen). Cells along a ray up to the obstacle are free, the cell at
the obstacle is occupied, the rest stays unknown. Occupied wins: a wall seen once from one side is
not erased by a grazing ray from another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

UNKNOWN, FREE, OCCUPIED = 0, 1, 2


@dataclass
class OccupancyGrid:
    """A floor's grid: ``cells[i, j]`` covers x in [x0 + i*cell, ...), y in [y0 + j*cell, ...)."""

    cells: np.ndarray  # (NX, NY) uint8 of UNKNOWN / FREE / OCCUPIED
    origin_m: np.ndarray  # (2,) x0, y0
    cell_m: float
    floor_z_m: float

    def to_index(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) world xy -> (N, 2) integer cell indices (may be out of the grid)."""
        return np.floor((np.asarray(xy)[..., :2] - self.origin_m) / self.cell_m).astype(np.int64)

    def centres(self, idx: np.ndarray) -> np.ndarray:
        """(N, 2) cell indices -> (N, 3) world centres on this floor."""
        xy = self.origin_m + (np.asarray(idx) + 0.5) * self.cell_m
        return np.column_stack([xy, np.full(len(xy), self.floor_z_m)])

    def inside(self, idx: np.ndarray) -> np.ndarray:
        nx_, ny_ = self.cells.shape
        return (idx[..., 0] >= 0) & (idx[..., 0] < nx_) & (idx[..., 1] >= 0) & (idx[..., 1] < ny_)

    @property
    def free(self) -> np.ndarray:
        return self.cells == FREE

    @property
    def occupied(self) -> np.ndarray:
        return self.cells == OCCUPIED

    def clearance_m(self) -> np.ndarray:
        """Distance of every cell centre to the nearest occupied or unknown cell (metres).

        Unknown counts as an obstacle: the planner must not send the robot where nobody looked.
        """
        return ndimage.distance_transform_edt(self.free) * self.cell_m

    def area_m2(self) -> float:
        return float(self.free.sum()) * self.cell_m**2


def build_occupancy(
    positions_m: np.ndarray,
    obstacle_m: np.ndarray,
    angles_rad: np.ndarray,
    headings_rad: np.ndarray,
    floor_z_m: float,
    cell_m: float = 0.1,
    max_range_m: float = 5.0,
    pad_m: float = 0.5,
    chunk_samples: int = 4_000_000,
) -> OccupancyGrid:
    """Ray-cast the scans of one floor into an occupancy grid.

    ``positions_m`` (S, 3), ``obstacle_m`` (S, A) ranges per relative angle ``angles_rad`` (A,),
    ``headings_rad`` (S,) the agent headings the angles are relative to. ``chunk_samples`` bounds
    the ray samples held at once (memory only: the grid does not depend on it).
    """
    positions_m = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    obstacle_m = np.asarray(obstacle_m, dtype=np.float64).reshape(len(positions_m), -1)
    lo = positions_m[:, :2].min(axis=0) - max_range_m - pad_m
    hi = positions_m[:, :2].max(axis=0) + max_range_m + pad_m
    shape = tuple(np.ceil((hi - lo) / cell_m).astype(int))
    grid = OccupancyGrid(np.zeros(shape, np.uint8), lo, cell_m, floor_z_m)
    if len(positions_m) == 0:
        return grid

    step = cell_m * 0.5
    samples = np.arange(0.0, max_range_m, step)  # (R,)
    world_ang = headings_rad[:, None] + angles_rad[None, :]  # (S, A)
    dirs = np.stack([np.cos(world_ang), np.sin(world_ang)], axis=-1)  # (S, A, 2)
    seen = ~np.isnan(obstacle_m)
    rng = np.where(np.isfinite(obstacle_m), obstacle_m, max_range_m)
    # Free: samples strictly before the obstacle (half a cell of margin keeps walls occupied).
    # Only the free samples are ever computed, a few scans at a time (all samples of a large
    # building's scans at once are hundreds of MB), each chunk as far out as its longest free ray
    # needs (one sample more for rounding: the exact test below decides).
    n_free = np.where(seen, np.clip(np.ceil((rng - cell_m * 0.5) / step), 0, len(samples)), 0).astype(np.int64)
    free_any = np.zeros(shape, dtype=bool)
    flat_free = free_any.ravel()
    ny_ = shape[1]
    n_ang = len(angles_rad)
    cos_f, sin_f = dirs[..., 0].ravel(), dirs[..., 1].ravel()
    chunk = max(1, chunk_samples // max(1, len(angles_rad) * len(samples)))
    for s0 in range(0, len(positions_m), chunk):
        sl = slice(s0, s0 + chunk)
        k_max = min(int(n_free[sl].max(initial=0)) + 1, len(samples))
        r = samples[:k_max]
        mask = seen[sl, :, None] & (r[None, None, :] < (rng[sl, :, None] - cell_m * 0.5))
        ray, ri = np.nonzero(mask.reshape(-1, k_max))
        ray += s0 * n_ang
        si, d = ray // n_ang, r[ri]
        # Per axis on flat arrays: the same arithmetic as OccupancyGrid.to_index, without gathers
        # of (N, 2) rows.
        ix = np.floor((positions_m[si, 0] + cos_f[ray] * d - lo[0]) / cell_m).astype(np.int64)
        iy = np.floor((positions_m[si, 1] + sin_f[ray] * d - lo[1]) / cell_m).astype(np.int64)
        ok = (ix >= 0) & (ix < shape[0]) & (iy >= 0) & (iy < ny_)
        flat_free[ix[ok] * ny_ + iy[ok]] = True

    hit = seen & np.isfinite(obstacle_m) & (obstacle_m < max_range_m)
    # The obstacle range is the near edge of its profile bin: the wall lies just beyond it.
    hit_rng = np.where(hit, obstacle_m, 0.0)  # inf/nan never enter the arithmetic
    hpts = positions_m[:, None, :2] + dirs * (hit_rng[..., None] + cell_m * 0.5)
    hidx = grid.to_index(hpts[hit])
    ok = grid.inside(hidx)
    occ_any = np.zeros(shape, dtype=bool)
    occ_any[hidx[ok, 0], hidx[ok, 1]] = True

    cells = np.zeros(shape, np.uint8)
    cells[free_any] = FREE
    cells[occ_any] = OCCUPIED
    # The cell under each scan position is free however the rays fell.
    own = grid.to_index(positions_m[:, :2])
    ok = grid.inside(own)
    cells[own[ok, 0], own[ok, 1]] = FREE
    grid.cells = cells
    return grid


def line_of_sight(blocked: np.ndarray, a_idx: np.ndarray, b_idx: np.ndarray, samples: int = 0) -> np.ndarray:
    """For pairs of cells (N, 2) and (N, 2): True where no blocked cell lies on the segment."""
    a = np.asarray(a_idx, dtype=np.float64)
    b = np.asarray(b_idx, dtype=np.float64)
    n = samples or int(np.ceil(np.max(np.abs(b - a), initial=1.0) * 2)) + 1
    t = np.linspace(0.0, 1.0, n)
    pts = np.rint(a[:, None, :] + (b - a)[:, None, :] * t[None, :, None]).astype(np.int64)
    nx_, ny_ = blocked.shape
    pts[..., 0] = np.clip(pts[..., 0], 0, nx_ - 1)
    pts[..., 1] = np.clip(pts[..., 1], 0, ny_ - 1)
    return ~blocked[pts[..., 0], pts[..., 1]].any(axis=1)
