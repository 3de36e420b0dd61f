"""Where the floor is under a point of the map: anticipated views at the candidate's own height.

A candidate on the stairs or on another storey must be rendered from its own floor, not from the
agent's (a camera 0.9 m under the tread it stands on looks at the underside of the stairs). The
map tells where one can stand: a *standing surface* is an occupied height bin of a
``cell_m`` x ``cell_m`` column with no point in the ``clearance_m`` above it (a floor, a stair
tread, the top of a low piece of furniture). A view's floor is the standing surface nearest to the
height it was asked at, within ``search_m``, in the column under it or, where that column holds
none (the floor under an agent is rarely in its own map), in the nearest columns around it.
"""

from __future__ import annotations

import numpy as np

from libs.pointrender.cloud import IndexedCloud


class FloorHeights:
    """Standing surfaces of a map, built once per map (cached on the index by :func:`floors_of`)."""

    def __init__(self, xyz: np.ndarray, cell_m: float = 0.1, bin_m: float = 0.05, clearance_m: float = 1.0,
                 neighbourhood_cells: int = 3):
        self.cell_m, self.bin_m, self.reach = float(cell_m), float(bin_m), int(neighbourhood_cells)
        self.lo = xyz.min(axis=0).astype(np.float64) - cell_m
        ij = np.floor((xyz[:, :2] - self.lo[:2]) / cell_m).astype(np.int64)
        k = np.floor((xyz[:, 2] - self.lo[2]) / bin_m).astype(np.int64)
        self._stride = int(ij[:, 1].max()) + 2 * self.reach + 4  # > any column index j asked for
        self.nz = int(k.max()) + 2 + int(np.ceil(clearance_m / bin_m))
        keys = (ij[:, 0] * self._stride + ij[:, 1]) * self.nz + k
        occupied, inverse = np.unique(keys, return_inverse=True)
        mean_z = np.bincount(inverse, weights=xyz[:, 2]) / np.bincount(inverse)
        # Free above: none of the bins 2 .. clearance/bin above is occupied (the next bin may hold
        # the same surface's noise).
        free = np.ones(len(occupied), bool)
        for j in range(2, int(np.ceil(clearance_m / bin_m)) + 1):
            free &= ~np.isin(occupied + j, occupied, assume_unique=True)
        self._keys = occupied[free]  # sorted by (column, bin)
        self._z = mean_z[free]  # mean height of the surface's points

    def floor_z(self, x_m: float, y_m: float, z_hint_m: float, search_m: float) -> float:
        """The standing surface nearest to ``z_hint_m`` within ``search_m`` under (x, y); the
        hint itself where the map shows none."""
        i = int(np.floor((x_m - self.lo[0]) / self.cell_m))
        j = int(np.floor((y_m - self.lo[1]) / self.cell_m))
        best, best_ring = None, None
        for ring in range(self.reach + 1):
            for di in range(-ring, ring + 1):
                for dj in range(-ring, ring + 1):
                    if max(abs(di), abs(dj)) != ring:
                        continue
                    z = self._nearest_in_column(i + di, j + dj, z_hint_m, search_m)
                    if z is not None and (best is None or abs(z - z_hint_m) < abs(best - z_hint_m)):
                        best, best_ring = z, ring
            if best_ring is not None:  # the nearest ring with a surface decides
                return best
        return z_hint_m

    def _nearest_in_column(self, i: int, j: int, z_hint_m: float, search_m: float) -> float | None:
        if i < 0 or j < 0 or j >= self._stride:
            return None
        base = (i * self._stride + j) * self.nz
        a, b = np.searchsorted(self._keys, [base, base + self.nz])
        if a == b:
            return None
        z = self._z[a:b]
        d = np.abs(z - z_hint_m)
        k = int(np.argmin(d))
        return float(z[k]) if d[k] <= search_m else None


def floors_of(index: IndexedCloud) -> FloorHeights:
    key = ("floor-heights",)
    if key not in index.cache:
        index.cache[key] = FloorHeights(index.cloud.xyz)
    return index.cache[key]
