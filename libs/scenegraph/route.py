"""Routes over a scene graph's walkable space: geodesic distances to a goal, on every floor at once.

The graph's :class:`~shared.schemas.FloorGrid` rasters become one graph (8-neighbour cells of a floor;
a stairs cell joined to the same cell one floor up). One Dijkstra from the goal gives the distance of
every cell to it: the route from anywhere is the descent of that field, so re-planning when the robot
leaves the route costs nothing (its new cell already has its distance).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from shared.schemas import SceneGraph

_SNAP_M = 1.0  # a point off the walkable cells (furniture, a wall's edge) snaps to one within this
_MAX_FIELDS = 64  # distance fields kept per router (one per goal or start asked for)
_STAIRS_REACH_M = 4.0  # a point this far above a floor's stairs cell may still be on those stairs


class Router:
    """Geodesic distances on a scene graph's walkable cells."""

    def __init__(self, graph: SceneGraph):
        self.grids = graph.free_space
        self.floors_z = np.array([g.z_m for g in self.grids], float)
        self._floors_list = [float(g.z_m) for g in self.grids]
        self._offset: list[int] = []
        self._index: list[np.ndarray] = []  # per floor: cell -> node index (-1 blocked)
        self._snap: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        rows, cols, w = [], [], []
        self._cells: list[np.ndarray] = []  # per floor: (floor, i, j) of each node, in node order
        n = 0
        for g in self.grids:
            walk = g.cells > 0
            idx = np.full(walk.shape, -1, np.int64)
            idx[walk] = np.arange(n, n + int(walk.sum()))
            self._offset.append(n)
            self._index.append(idx)
            n += int(walk.sum())
            dist, (ni, nj) = ndimage.distance_transform_edt(~walk, return_indices=True)
            self._snap.append((dist * g.cell_m, ni, nj))
            ci, cj = np.nonzero(walk)
            self._cells.append(np.c_[np.full(len(ci), len(self._cells)), ci, cj])
            pad = np.pad(idx, 1, constant_values=-1)
            a = pad[1:-1, 1:-1]
            for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
                b = pad[1 + di: pad.shape[0] - 1 + di, 1 + dj: pad.shape[1] - 1 + dj]
                ok = (a >= 0) & (b >= 0)
                rows.append(a[ok]), cols.append(b[ok])
                w.append(np.full(int(ok.sum()), g.cell_m * math.hypot(di, dj)))
        for k in range(len(self.grids) - 1):
            lo, hi = self.grids[k], self.grids[k + 1]
            if lo.cells.shape != hi.cells.shape:
                continue
            up = (lo.cells == 2) & (hi.cells > 0)
            a, b = self._index[k][up], self._index[k + 1][up]
            rows.append(a), cols.append(b), w.append(np.full(len(a), max(hi.z_m - lo.z_m, lo.cell_m)))
        self.n = n
        # Per node: its room (index into graph.rooms, -1 none) and its centre; what a route's reading needs
        # for every cell it passes (a lookup per point was a third of a grounding).
        self.node_room = np.concatenate([g.rooms[g.cells > 0] if g.rooms is not None
                                         else np.full(int((g.cells > 0).sum()), -1) for g in self.grids]
                                        ).astype(np.int64) if self.grids else np.zeros(0, np.int64)
        self._stairs_floors = [f for f, g in enumerate(self.grids) if (g.cells == 2).any()]
        self._node_cell = np.concatenate(self._cells) if self._cells else np.zeros((0, 3), np.int64)
        r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        c = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        ww = np.concatenate(w) if w else np.zeros(0)
        self._csr = coo_matrix((np.r_[ww, ww], (np.r_[r, c], np.r_[c, r])), shape=(n, n)).tocsr()
        self._fields: dict[int, np.ndarray] = {}

    def floor_of(self, xyz) -> int:
        """The floor a point stands on: the highest floor at most 0.8 m above it."""
        if len(self.floors_z) == 0:
            return -1
        z = float(xyz[2]) + 0.8
        f = 0
        for k, fz in enumerate(self._floors_list):  # a handful of floors: no array call per point
            if fz <= z:
                f = k
        return f

    def node_of(self, xyz, snap_m: float = _SNAP_M) -> int | None:
        """The walkable cell of a point (snapped within ``snap_m``), or None."""
        f = self.floor_of(xyz)
        if f < 0:
            return None
        g = self.grids[f]
        i = int(math.floor((float(xyz[0]) - g.origin_m[0]) / g.cell_m))
        j = int(math.floor((float(xyz[1]) - g.origin_m[1]) / g.cell_m))
        if not (0 <= i < g.cells.shape[0] and 0 <= j < g.cells.shape[1]):
            return None
        dist, ni, nj = self._snap[f]
        if dist[i, j] > snap_m:
            return None
        node = self._index[f][ni[i, j], nj[i, j]]
        return int(node) if node >= 0 else None

    def field(self, goal_xyz, snap_m: float = 2.0) -> np.ndarray | None:
        """Distance of every walkable cell to ``goal_xyz`` (inf where unreachable); None when the goal is
        off the walkable space (further than ``snap_m``: an object's centre lies inside its footprint)."""
        node = self.node_of(goal_xyz, snap_m)
        if node is None:
            return None
        if node not in self._fields:
            if len(self._fields) >= _MAX_FIELDS:  # a router lives as long as its map: bound what it keeps
                self._fields.pop(next(iter(self._fields)))
            self._fields[node] = dijkstra(self._csr, directed=False, indices=node)
        return self._fields[node]

    def distance(self, field: np.ndarray, xyz) -> float:
        """Route distance of ``xyz`` to the field's goal. On stairs a point's height does not tell its floor
        (a move down the stairs is proposed at the robot's height): a stairs cell of any floor under the
        point counts too, and the shorter distance wins."""
        node = self.node_of(xyz)
        d = math.inf if node is None else float(field[node])
        for f in self._stairs_floors:
            g = self.grids[f]
            i = int(math.floor((float(xyz[0]) - g.origin_m[0]) / g.cell_m))
            j = int(math.floor((float(xyz[1]) - g.origin_m[1]) / g.cell_m))
            if 0 <= i < g.cells.shape[0] and 0 <= j < g.cells.shape[1] and g.cells[i, j] == 2 \
                    and -0.5 < float(xyz[2]) - g.z_m < _STAIRS_REACH_M:
                k = self._index[f][i, j]
                if k >= 0:
                    d = min(d, float(field[k]))
        return d

    def position(self, node: int) -> np.ndarray:
        return self.positions(np.array([node]))[0]

    def positions(self, nodes) -> np.ndarray:
        """(n, 3) centres of the cells ``nodes``."""
        fij = self._node_cell[np.asarray(nodes, np.int64)]
        org = np.array([[g.origin_m[0], g.origin_m[1], g.cell_m, g.z_m] for g in self.grids])[fij[:, 0]]
        return np.c_[org[:, 0] + (fij[:, 1] + 0.5) * org[:, 2], org[:, 1] + (fij[:, 2] + 0.5) * org[:, 2], org[:, 3]]

    def path_nodes(self, field: np.ndarray, start_xyz, max_nodes: int = 10_000, snap_m: float = _SNAP_M) -> list[int]:
        """The nodes from ``start_xyz`` down the field to its origin (empty when unreachable)."""
        node = self.node_of(start_xyz, snap_m)
        if node is None or not np.isfinite(field[node]):
            return []
        out = [node]
        indptr, indices = self._csr.indptr, self._csr.indices
        while field[node] > 0 and len(out) < max_nodes:
            nb = indices[indptr[node]: indptr[node + 1]]
            nxt = int(nb[np.argmin(field[nb])])
            if field[nxt] >= field[node]:
                break
            node = nxt
            out.append(node)
        return out

    def path(self, field: np.ndarray, start_xyz, max_nodes: int = 10_000) -> list[np.ndarray]:
        """The cells from ``start_xyz`` down the field to its goal (empty when unreachable)."""
        out = self.path_nodes(field, start_xyz, max_nodes)
        if not out:
            return []
        return list(self.positions(out[::2] + [out[-1]]))
