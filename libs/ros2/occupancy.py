"""Geodesic distances and paths on a nav_msgs/OccupancyGrid (8-connected Dijkstra over free cells)."""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.ndimage import binary_dilation
from scipy.sparse.csgraph import dijkstra


class OccupancyPlanner:
    def __init__(self, free: np.ndarray, resolution_m: float, origin_xy_m: tuple[float, float]):
        self.free, self.res, self.origin = free, float(resolution_m), np.asarray(origin_xy_m, np.float64)
        h, w = free.shape
        idx = -np.ones((h, w), np.int64)
        cells = np.argwhere(free)
        idx[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
        self._idx, self._cells = idx, cells
        rows, cols, wts = [], [], []
        for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = cells
            b = a + (di, dj)
            ok = (b[:, 0] >= 0) & (b[:, 0] < h) & (b[:, 1] >= 0) & (b[:, 1] < w)
            a, b = a[ok], b[ok]
            nb = idx[b[:, 0], b[:, 1]]
            ok2 = nb >= 0
            rows.append(idx[a[ok2, 0], a[ok2, 1]])
            cols.append(nb[ok2])
            wts.append(np.full(int(ok2.sum()), self.res * math.hypot(di, dj)))
        r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(wts)
        self._graph = sparse.coo_matrix((v, (r, c)), shape=(len(cells), len(cells))).tocsr()

    @classmethod
    def from_msg(cls, msg, robot_radius_m: float = 0.0) -> OccupancyPlanner:
        info = msg.info
        grid = np.asarray(msg.data, np.int8).reshape(int(info.height), int(info.width))
        blocked = (grid < 0) | (grid >= 50)
        r = int(round(robot_radius_m / float(info.resolution)))
        if r > 0:  # a cell is free for the robot only with its footprint clear
            blocked = binary_dilation(blocked, iterations=r)
        return cls(~blocked, float(info.resolution), (float(info.origin.position.x), float(info.origin.position.y)))

    def _cell(self, p) -> int:
        j, i = np.floor((np.asarray(p, np.float64)[:2] - self.origin) / self.res).astype(int)
        h, w = self.free.shape
        if 0 <= i < h and 0 <= j < w and self._idx[i, j] >= 0:
            return int(self._idx[i, j])
        # Off the free space (a waypoint on an obstacle's edge): the nearest free cell within 0.5 m.
        d = np.hypot(*(self._cells[:, ::-1] - np.array([j, i])).T) * self.res
        k = int(np.argmin(d))
        return k if d[k] <= 0.5 else -1

    def distance(self, a, b) -> float:
        s, g = self._cell(a), self._cell(b)
        if s < 0 or g < 0:
            return math.inf
        return float(dijkstra(self._graph, directed=False, indices=s)[g])

    def path(self, a, b) -> np.ndarray | None:
        s, g = self._cell(a), self._cell(b)
        if s < 0 or g < 0:
            return None
        dist, pred = dijkstra(self._graph, directed=False, indices=s, return_predecessors=True)
        if not np.isfinite(dist[g]):
            return None
        out = [g]
        while out[-1] != s:
            out.append(int(pred[out[-1]]))
        cells = self._cells[out[::-1]]
        xy = self.origin + (cells[:, ::-1] + 0.5) * self.res
        return np.column_stack([xy, np.zeros(len(xy))])
