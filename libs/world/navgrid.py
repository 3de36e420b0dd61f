"""Navigation grid of a scene's walkable surface, for a cylinder agent, on any number of floors.

Built from the mesh alone (so it works for generated houses and scanned meshes alike):

1. **Floor candidates.** A downward ray per grid column lists every surface it crosses; a roughly
   horizontal surface is a candidate floor when the next surface above it is at least the agent
   height away (this also rejects the space under tables and the tops of walls).
2. **Footprint.** A node survives only if every column within the agent radius holds a floor at a
   height it can step to (``|dz| <= max_climb``): the agent never hangs over a drop or a table edge.
3. **Obstacles.** Points sampled on the non-horizontal triangles (walls, furniture sides, also
   zero-thickness walls of scans) block a node when one lies within the radius at a height between
   ``max_climb`` and ``height`` above it.
4. **Graph.** 8-connected nodes whose heights differ by at most ``max_climb`` (diagonals only when
   both orthogonal neighbours exist, so paths never cut corners); stairs are ordinary edges.
5. **Stray regions.** Disconnected regions that stand less than the agent height above the next
   surface below (table, bed and counter tops) or are smaller than ``min_region_area_m2`` are
   removed: only floors remain walkable.

Geodesic distances are Dijkstra over that graph (distance fields cached per source node); paths are
shortened by line-of-sight on the same grid. ``segment_clear`` is the collision model that
``SimRobot.move_to`` uses, so the robot and the metrics agree on where the agent can be.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import NavigationError
from .scene import Scene

if TYPE_CHECKING:
    import open3d as o3d

log = logging.getLogger(__name__)

# Obstacle sample points generated at a time (see NavGrid._prune_obstacles): a chunk's temporaries
# are a few MB, not hundreds.
_SAMPLE_CHUNK = 1 << 16


@dataclass(frozen=True)
class AgentShape:
    """The agent's collision cylinder (the VLN-CE defaults)."""

    radius_m: float = 0.1
    height_m: float = 1.5
    max_climb_m: float = 0.2


class NavGrid:
    """Walkable nodes on a regular xy grid with per-column floor levels."""

    # The obstacle pass and walk() as compiled loops when numba is installed (False, on the class or
    # an instance: the array versions, the same results).
    use_kernel = True

    def __init__(
        self,
        scene: Scene,
        agent: AgentShape = AgentShape(),
        cell_m: float = 0.05,
        raycasting_scene: o3d.t.geometry.RaycastingScene | None = None,
        max_slope_deg: float = 30.0,
        obstacle_density_per_m2: float = 1500.0,
        seed: int = 0,
        min_region_area_m2: float = 1.0,
    ):
        self.agent = agent
        self.cell_m = float(cell_m)
        lo, hi = scene.bounds_m
        self.origin = np.floor(lo[:2] / cell_m) * cell_m
        self.shape = tuple(int(v) for v in np.ceil((hi[:2] - self.origin) / cell_m).astype(int) + 1)
        self._z_top = float(hi[2]) + 1.0
        rc = raycasting_scene
        if rc is None:
            from shared.o3d import o3d  # here, not at module level: open3d costs ~0.4 s of CPU at every process start

            rc = o3d.t.geometry.RaycastingScene()
            rc.add_triangles(
                o3d.t.geometry.TriangleMesh(
                    o3d.core.Tensor(scene.vertices.astype(np.float32)), o3d.core.Tensor(scene.triangles)
                )
            )
        v = scene.vertices[scene.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        area2 = np.linalg.norm(n, axis=1)
        nz = np.abs(n[:, 2]) / np.maximum(area2, 1e-12)
        cos_slope = np.cos(np.radians(max_slope_deg))
        # Up/down facing from the winding; scanned meshes with mixed winding are treated as unknown.
        signed = n[:, 2] / np.maximum(area2, 1e-12)
        horiz = nz >= cos_slope
        consistent = scene.consistent_winding
        self._up = np.where(signed > 0, 1, -1) if consistent else np.zeros(len(n), dtype=np.int64)
        self._up = np.where(horiz, self._up, 0)
        self._build_levels(rc, nz >= cos_slope)
        self._prune_footprint()
        self._prune_obstacles(v[nz < cos_slope], area2[nz < cos_slope] / 2.0, obstacle_density_per_m2, seed)
        self._build_graph()
        self.min_region_area_m2 = float(min_region_area_m2)
        if self._drop_stray_regions():
            self._build_graph()
        self._fields: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        if len(self.nodes_m):
            self.walk(self.nodes_m[0], self.nodes_m[0])  # compiles (or loads) the kernel now, not on a request
        log.info(
            "nav grid %dx%d @ %.2f m: %d nodes, %d components, main %.1f m2",
            *self.shape, self.cell_m, len(self.nodes_m), self.n_components, self.reachable_area_m2,
        )

    # --- construction --------------------------------------------------------------------------------

    def _build_levels(self, rc, floorlike: np.ndarray) -> None:
        nx_, ny_ = self.shape
        ix, iy = np.meshgrid(np.arange(nx_), np.arange(ny_), indexing="ij")
        xy = self.origin + (np.stack([ix, iy], -1).reshape(-1, 2) + 0.5) * self.cell_m
        rays = np.zeros((len(xy), 6), np.float32)
        rays[:, :2] = xy
        rays[:, 2] = self._z_top
        rays[:, 5] = -1.0
        from shared.o3d import o3d  # only binds the name: rc is a RaycastingScene, so open3d is loaded already
        hits = rc.list_intersections(o3d.core.Tensor(rays))
        ray_ids = hits["ray_ids"].numpy().astype(np.int64)
        z = self._z_top - hits["t_hit"].numpy().astype(np.float64)
        prim = hits["primitive_ids"].numpy().astype(np.int64)
        # list_intersections does not promise an order along the ray: sort by ray, then descending z.
        order = np.lexsort((-z, ray_ids))
        ray_ids, z, prim = ray_ids[order], z[order], prim[order]
        up = self._up[prim]
        same_prev = np.r_[False, ray_ids[1:] == ray_ids[:-1]]
        # Clearance: distance to the nearest surface strictly above (ties are the same surface hit
        # twice on a shared edge, or two coincident faces).
        z_above = np.full(len(z), np.inf)
        for lag in (1, 2, 3):
            prev_same = np.zeros(len(z), dtype=bool)
            prev_same[lag:] = ray_ids[lag:] == ray_ids[:-lag]
            zp = np.full(len(z), np.inf)
            zp[lag:] = z[:-lag]
            cand = prev_same & (zp > z + 1e-3) & ~np.isfinite(z_above)
            z_above[cand] = zp[cand]
        # Height above the next surface below: a walkable region that stands less than the agent's
        # height above something (a table or bed top) is furniture, not floor.
        z_below = np.full(len(z), -np.inf)
        for lag in (1, 2, 3):
            nxt_same = np.zeros(len(z), dtype=bool)
            nxt_same[:-lag] = ray_ids[:-lag] == ray_ids[lag:]
            zn = np.full(len(z), -np.inf)
            zn[:-lag] = z[lag:]
            cand = nxt_same & (zn < z - 1e-3) & ~np.isfinite(z_below)
            z_below[cand] = zn[cand]
        # A floor face coincident with a downward face (the bottom of a box standing on it) is covered.
        tied_down = np.zeros(len(z), dtype=bool)
        for lag in (1, 2):
            for sgn in (1, -1):
                j = np.arange(len(z)) - sgn * lag
                valid = (j >= 0) & (j < len(z))
                jj = np.clip(j, 0, max(len(z) - 1, 0))
                tied_down |= valid & (ray_ids[jj] == ray_ids) & (np.abs(z[jj] - z) < 1e-3) & (up[jj] < 0)
        ok = floorlike[prim] & (up >= 0) & ~tied_down & (z_above - z >= self.agent.height_m)
        # A topmost surface above another floor candidate of its column is a roof, not a floor.
        ok_idx = np.flatnonzero(ok)
        roof = np.zeros(len(z), dtype=bool)
        if len(ok_idx) > 1:
            nxt_same = np.r_[ray_ids[ok_idx][1:] == ray_ids[ok_idx][:-1], False]
            roof[ok_idx] = ~np.isfinite(z_above[ok_idx]) & nxt_same
        ok &= ~roof
        del same_prev
        col = ray_ids[ok]
        zz = z[ok]
        # Columns may hold several floors (storeys, a table top with headroom); keep them all.
        k = np.zeros(len(col), dtype=np.int64)
        if len(col):
            starts = np.r_[0, np.flatnonzero(col[1:] != col[:-1]) + 1]
            k = np.arange(len(col)) - np.repeat(starts, np.diff(np.r_[starts, len(col)]))
        self.levels = int(k.max()) + 1 if len(k) else 1
        self._zgrid = np.full((nx_ * ny_, self.levels), np.nan)
        self._zgrid[col, k] = zz
        self._zgrid = self._zgrid.reshape(nx_, ny_, self.levels)
        self._gapgrid = np.full((nx_ * ny_, self.levels), np.inf)
        self._gapgrid[col, k] = zz - z_below[ok]
        self._gapgrid = self._gapgrid.reshape(nx_, ny_, self.levels)

    def _node_arrays(self):
        ix, iy, k = np.nonzero(~np.isnan(self._zgrid))
        return ix, iy, k, self._zgrid[ix, iy, k]

    def _offsets(self, radius_m: float) -> np.ndarray:
        r = int(np.ceil(radius_m / self.cell_m))
        d = np.arange(-r, r + 1)
        ox, oy = np.meshgrid(d, d, indexing="ij")
        keep = np.hypot(ox, oy) * self.cell_m <= radius_m + 1e-9
        return np.stack([ox[keep], oy[keep]], axis=1)

    def _shifted_z(self, ix, iy, dx, dy) -> np.ndarray:
        """Levels of column (ix+dx, iy+dy), (N, K); NaN outside the grid."""
        jx, jy = ix + dx, iy + dy
        inside = (jx >= 0) & (jx < self.shape[0]) & (jy >= 0) & (jy < self.shape[1])
        out = np.full((len(ix), self.levels), np.nan)
        out[inside] = self._zgrid[jx[inside], jy[inside]]
        return out

    def _prune_footprint(self) -> None:
        ix, iy, k, z = self._node_arrays()
        keep = np.ones(len(z), dtype=bool)
        for dx, dy in self._offsets(self.agent.radius_m):
            zs = self._shifted_z(ix, iy, dx, dy)
            keep &= np.any(np.abs(zs - z[:, None]) <= self.agent.max_climb_m, axis=1)
        self._zgrid[ix[~keep], iy[~keep], k[~keep]] = np.nan

    def _prune_obstacles(self, tris: np.ndarray, areas: np.ndarray, density: float, seed: int) -> None:
        if len(tris) == 0:
            return
        rng = np.random.default_rng(seed)
        counts = rng.poisson(areas * density)
        counts = np.maximum(counts, 1)  # thin slivers (chair legs) still leave a mark
        idx = np.repeat(np.arange(len(tris)), counts)
        r1 = np.sqrt(rng.random(len(idx)))
        r2 = rng.random(len(idx))
        ix, iy, k, z = self._node_arrays()
        # Conservative disk: a point anywhere in a column whose centre is within r + half a cell.
        offsets = self._offsets(self.agent.radius_m + 0.5 * self.cell_m * np.sqrt(2))
        blocked = None
        kernel = _compiled("obstacles") if self.use_kernel else None
        if kernel is not None:
            blocked = np.zeros(len(z), dtype=bool)
            if kernel(tris, idx, r1, r2, self.origin, self.cell_m, self.shape[0], self.shape[1], ix, iy, z, offsets,
                      self.agent.max_climb_m, self.agent.height_m, blocked) < 0:
                blocked = None  # a case the kernel does not decide (see _obstacle_kernel): the array code does
        if blocked is None:
            blocked = self._blocked_numpy(tris, idx, r1, r2, ix, iy, z, offsets)
        self._zgrid[ix[blocked], iy[blocked], k[blocked]] = np.nan

    def _blocked_numpy(self, tris, idx, r1, r2, ix, iy, z, offsets) -> np.ndarray:
        """The nodes that an obstacle point blocks, as arrays (the reference :func:`_obstacle_kernel` equals)."""
        # The points in chunks, each with the same arithmetic as all at once (the same bits): a 500 m2
        # house samples 5.1e6 points, and its (N, 3, 3) corners and (N, 3) points whole were 370 and
        # 120 MB of temporaries that the arithmetic streamed through memory (2.3 s of its 4.5 s build).
        colid = np.empty(len(idx), np.int64)
        pz = np.empty(len(idx))
        inside = np.empty(len(idx), bool)
        for s in range(0, len(idx), _SAMPLE_CHUNK):
            a, b = r1[s : s + _SAMPLE_CHUNK], r2[s : s + _SAMPLE_CHUNK]
            t = tris[idx[s : s + _SAMPLE_CHUNK]]
            pts = (1 - a)[:, None] * t[:, 0] + (a * (1 - b))[:, None] * t[:, 1] + (a * b)[:, None] * t[:, 2]
            c = np.floor((pts[:, :2] - self.origin) / self.cell_m).astype(np.int64)
            inside[s : s + _SAMPLE_CHUNK] = ((c[:, 0] >= 0) & (c[:, 0] < self.shape[0])
                                             & (c[:, 1] >= 0) & (c[:, 1] < self.shape[1]))
            colid[s : s + _SAMPLE_CHUNK] = c[:, 0] * self.shape[1] + c[:, 1]
            pz[s : s + _SAMPLE_CHUNK] = pts[:, 2]
        colid, pz = colid[inside], pz[inside]
        zmin = float(pz.min()) - 1.0
        span = float(pz.max()) - zmin + 10.0
        keys = np.sort(colid * span + (pz - zmin))
        blocked = np.zeros(len(z), dtype=bool)
        for dx, dy in offsets:
            jx, jy = ix + dx, iy + dy
            inside = (jx >= 0) & (jx < self.shape[0]) & (jy >= 0) & (jy < self.shape[1])
            col = (jx * self.shape[1] + jy).astype(np.float64)
            lo = col * span + (z + self.agent.max_climb_m - zmin)
            hi = col * span + (z + self.agent.height_m - zmin)
            cnt = np.searchsorted(keys, hi) - np.searchsorted(keys, lo)
            blocked |= inside & (cnt > 0)
        return blocked

    def _build_graph(self) -> None:
        # scipy's graph and tree modules load here, with open3d: importing libs.world stays cheap for the CLIs
        from scipy import sparse
        from scipy.sparse import csgraph
        from scipy.spatial import cKDTree

        ix, iy, k, z = self._node_arrays()
        self.nodes_m = np.column_stack([self.origin[0] + (ix + 0.5) * self.cell_m, self.origin[1] + (iy + 0.5) * self.cell_m, z])
        self._ijk = np.column_stack([ix, iy, k])
        nid = np.full(self._zgrid.shape, -1, dtype=np.int64)
        nid[ix, iy, k] = np.arange(len(z))
        self._nid = nid
        rows, cols = [], []
        climb = self.agent.max_climb_m

        def neighbour(dx, dy):
            """For each node, the id of the step-compatible node in column (ix+dx, iy+dy), or -1."""
            zs = self._shifted_z(ix, iy, dx, dy)
            dz = np.abs(zs - z[:, None])
            dz[np.isnan(dz)] = np.inf
            kk = np.argmin(dz, axis=1)
            ok = dz[np.arange(len(z)), kk] <= climb
            out = np.full(len(z), -1, dtype=np.int64)
            out[ok] = nid[ix[ok] + dx, iy[ok] + dy, kk[ok]]
            return out

        nb = {(dx, dy): neighbour(dx, dy) for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))}
        for (dx, dy), other in nb.items():
            ok = other >= 0
            if dx != 0 and dy != 0:
                ok &= (nb[(dx, 0)] >= 0) & (nb[(0, dy)] >= 0)
            rows.append(np.flatnonzero(ok))
            cols.append(other[ok])
        r = np.concatenate(rows)
        c = np.concatenate(cols)
        w = np.linalg.norm(self.nodes_m[r] - self.nodes_m[c], axis=1)
        n = len(z)
        g = sparse.coo_matrix((w, (r, c)), shape=(n, n)).tocsr()
        self.graph = g.maximum(g.T)  # symmetric even where a climb test differed by rounding
        self.n_components, self.component = csgraph.connected_components(self.graph, directed=False)
        sizes = np.bincount(self.component, minlength=self.n_components)
        self.main_component = int(np.argmax(sizes)) if n else -1
        self._tree = cKDTree(self.nodes_m * np.array([1.0, 1.0, 4.0]))  # floors far apart in z

    def _drop_stray_regions(self) -> int:
        """Remove walkable regions that are not floor: furniture tops and specks; returns how many.

        A region other than the largest goes when it is smaller than ``min_region_area_m2`` or when
        it stands (median over its cells) less than the agent's height above the next surface
        below it: a table, bed or counter top, which a real agent cannot climb onto anyway. Floors
        of other storeys and rooms cut off in a scan stand a storey high or on the ground, and stay.
        """
        if self.n_components <= 1:
            return 0
        ix, iy, k = self._ijk.T
        gap = self._gapgrid[ix, iy, k]
        sizes = np.bincount(self.component, minlength=self.n_components)
        area = sizes * self.cell_m**2
        order = np.argsort(self.component, kind="stable")
        starts = np.r_[0, np.cumsum(sizes)[:-1]]
        median_gap = np.array([np.median(gap[order[a : a + n]]) for a, n in zip(starts, sizes)])
        largest = int(np.argmax(sizes))
        drop = (area < self.min_region_area_m2) | (median_gap < self.agent.height_m)
        drop[largest] = False
        if not drop.any():
            return 0
        gone = drop[self.component]
        self._zgrid[ix[gone], iy[gone], k[gone]] = np.nan
        log.debug("dropped %d stray walkable regions (%d cells)", int(drop.sum()), int(gone.sum()))
        return int(drop.sum())

    # --- queries -------------------------------------------------------------------------------------

    @property
    def reachable_area_m2(self) -> float:
        """Area of the largest connected walkable region."""
        if self.main_component < 0:
            return 0.0
        return float(np.sum(self.component == self.main_component)) * self.cell_m**2

    def set_main_component_from(self, p) -> None:
        """Make the component under ``p`` (e.g. the start pose) the one sampling draws from."""
        self.main_component = int(self.component[self.nearest_node(p)])

    def locate(self, p, z_tol_m: float | None = None) -> int:
        """Node whose column contains ``p`` and whose floor is within step reach of p.z; -1 if none."""
        p = np.asarray(p, dtype=np.float64)
        ij = np.floor((p[:2] - self.origin) / self.cell_m).astype(np.int64)
        if np.any(ij < 0) or ij[0] >= self.shape[0] or ij[1] >= self.shape[1]:
            return -1
        zs = self._zgrid[ij[0], ij[1]]
        dz = np.abs(zs - p[2])
        dz[np.isnan(dz)] = np.inf
        k = int(np.argmin(dz))
        tol = self.agent.max_climb_m + 0.01 if z_tol_m is None else z_tol_m
        if dz[k] > tol:
            return -1
        return int(self._nid[ij[0], ij[1], k])

    def is_navigable(self, p, main_only: bool = False) -> bool:
        n = self.locate(p)
        return n >= 0 and (not main_only or self.component[n] == self.main_component)

    def nearest_node(self, p, main_only: bool = False) -> int:
        q = np.asarray(p, dtype=np.float64) * np.array([1.0, 1.0, 4.0])
        if not main_only:
            return int(self._tree.query(q)[1])
        ks = min(len(self.nodes_m), 64)
        while True:
            _, idx = self._tree.query(q, k=ks)
            idx = np.atleast_1d(idx)
            hit = idx[self.component[idx] == self.main_component]
            if len(hit):
                return int(hit[0])
            if ks >= len(self.nodes_m):
                raise NavigationError("no node in the main component")
            ks = min(len(self.nodes_m), ks * 8)

    def snap(self, p, main_only: bool = False) -> np.ndarray:
        """Nearest walkable point (a node position) to ``p``."""
        if len(self.nodes_m) == 0:
            raise NavigationError("the scene has no walkable surface for this agent")
        return self.nodes_m[self.nearest_node(p, main_only)].copy()

    def sample_navigable(self, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
        """Uniform random node position(s) of the main component."""
        ids = np.flatnonzero(self.component == self.main_component)
        pick = rng.choice(ids, size=n)
        return self.nodes_m[pick].copy()

    def _field(self, node: int) -> tuple[np.ndarray, np.ndarray]:
        if node in self._fields:
            self._fields.move_to_end(node)
            return self._fields[node]
        from scipy.sparse import csgraph  # loaded already by _build_graph; this binds the name

        dist, pred = csgraph.dijkstra(self.graph, directed=False, indices=node, return_predecessors=True)
        self._fields[node] = (dist, pred)
        if len(self._fields) > 16:
            self._fields.popitem(last=False)
        return dist, pred

    def _endpoint(self, p) -> int:
        n = self.locate(p, z_tol_m=0.5)
        return n if n >= 0 else self.nearest_node(p)

    def geodesic_distance(self, a, b) -> float:
        """Shortest walkable distance between two points (snapped to the grid); inf if unreachable.

        The snap offsets are added, so a point off the grid is not closer than it really is.
        """
        na, nb = self._endpoint(a), self._endpoint(b)
        d = self._field(nb)[0][na]
        if not np.isfinite(d):
            return float("inf")
        off_a = np.linalg.norm(self.nodes_m[na][:2] - np.asarray(a, dtype=float)[:2])
        off_b = np.linalg.norm(self.nodes_m[nb][:2] - np.asarray(b, dtype=float)[:2])
        return float(d + off_a + off_b)

    def shortest_path(self, a, b, smooth: bool = True) -> np.ndarray | None:
        """Walkable path from a to b as (P, 3) points (first = snapped a, last = snapped b); None if none."""
        na, nb = self._endpoint(a), self._endpoint(b)
        dist, pred = self._field(nb)
        if not np.isfinite(dist[na]):
            return None
        path = [na]
        while path[-1] != nb:
            path.append(int(pred[path[-1]]))
        pts = self.nodes_m[path]
        return self.smooth_path(pts) if smooth else pts

    def smooth_path(self, pts: np.ndarray) -> np.ndarray:
        """Greedy line-of-sight shortcutting; keeps the path on the walkable grid."""
        if len(pts) <= 2:
            return pts.copy()
        out = [pts[0]]
        i = 0
        while i < len(pts) - 1:
            # Furthest visible point by doubling then bisection: O(log n) segment checks per vertex.
            j = i + 1
            step = 1
            while j + step < len(pts) and self.segment_clear(pts[i], pts[j + step]):
                j += step
                step *= 2
            while step > 1:
                step //= 2
                if j + step < len(pts) and self.segment_clear(pts[i], pts[j + step]):
                    j += step
            out.append(pts[j])
            i = j
        return np.array(out)

    def segment_clear(self, a, b) -> bool:
        """True if the agent can walk straight from a to b (every sample on the grid, steps <= climb)."""
        return self.walk(a, b)[1]

    def walk(self, a, b) -> tuple[np.ndarray, bool]:
        """Walk straight from a towards b; returns (last reachable point with its floor z, reached b).

        Samples every half cell along the segment; at each the agent takes the level of that column
        nearest its current floor, and stops before one more than ``max_climb`` away. The robot calls
        this up to three times per 0.25 m sub-step, so it runs as one compiled loop (:func:`_walk_kernel`)
        when numba is there, with the same floating-point operations in the same order as the array
        version (:meth:`_walk_numpy`): the same points to the bit.
        """
        a = np.asarray(a, dtype=np.float64)
        b = np.asarray(b, dtype=np.float64)
        # The sample count from numpy's hypot, as the array version computes it (math.hypot may
        # round the last bit differently, and a count on an integer boundary would then differ).
        length = float(np.hypot(b[0] - a[0], b[1] - a[1]))
        kernel = _compiled("walk") if self.use_kernel else None
        if kernel is None:
            return self._walk_numpy(a, b, length)
        out = np.empty(3)
        status = kernel(a, b, length, self.origin, self.cell_m, self._zgrid, self._nid, self.nodes_m,
                                  self.agent.max_climb_m, self.agent.max_climb_m + 0.01, out)
        if status < 0:
            return a.copy(), False
        return out, bool(status)

    def _walk_numpy(self, a: np.ndarray, b: np.ndarray, length: float) -> tuple[np.ndarray, bool]:
        n0 = self.locate(a)
        if n0 < 0:
            return a.copy(), False
        n = max(1, int(np.ceil(length / (0.5 * self.cell_m))))
        ts = np.arange(1, n + 1) / n
        xy = a[:2] + ts[:, None] * (b[:2] - a[:2])
        ij = np.floor((xy - self.origin) / self.cell_m).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < self.shape[1])
        zcol = np.full((n, self.levels), np.nan)
        zcol[inside] = self._zgrid[ij[inside, 0], ij[inside, 1]]
        z = float(self.nodes_m[n0, 2])
        last = np.array([a[0], a[1], z])
        for s in range(n):
            dz = np.abs(zcol[s] - z)
            dz[np.isnan(dz)] = np.inf
            k = int(np.argmin(dz))
            if dz[k] > self.agent.max_climb_m:
                return last, False
            z = float(zcol[s, k])
            last = np.array([xy[s, 0], xy[s, 1], z])
        return last, True


def _nearest_level(zs, z):  # pragma: no cover - compiled
    """Index of the level nearest ``z`` (the first of ties, like argmin) and its distance; inf if none."""
    best = np.inf
    k = 0
    for lev in range(zs.shape[0]):
        d = abs(zs[lev] - z)
        if d < best:  # NaN (no floor at that level) never compares less
            best = d
            k = lev
    return k, best


def _walk_kernel(a, b, length, origin, cell, zgrid, nid, nodes, climb, locate_tol, out):  # pragma: no cover - compiled
    """:meth:`NavGrid._walk_numpy` as one loop: -1 when ``a`` is off the grid, else 1 if b was
    reached and 0 if not, with the last reachable point written to ``out``."""
    nx, ny = zgrid.shape[0], zgrid.shape[1]
    i = np.int64(np.floor((a[0] - origin[0]) / cell))
    j = np.int64(np.floor((a[1] - origin[1]) / cell))
    if i < 0 or j < 0 or i >= nx or j >= ny:
        return -1
    k, dz = _nearest_level(zgrid[i, j], a[2])
    if dz > locate_tol:
        return -1
    z = nodes[nid[i, j, k], 2]
    out[0] = a[0]
    out[1] = a[1]
    out[2] = z
    n = max(1, np.int64(np.ceil(length / (0.5 * cell))))
    dx = b[0] - a[0]
    dy = b[1] - a[1]
    for s in range(n):
        t = (s + 1) / n
        x = a[0] + t * dx
        y = a[1] + t * dy
        i = np.int64(np.floor((x - origin[0]) / cell))
        j = np.int64(np.floor((y - origin[1]) / cell))
        if i < 0 or j < 0 or i >= nx or j >= ny:
            return 0
        k, dz = _nearest_level(zgrid[i, j], z)
        if dz > climb:
            return 0
        z = zgrid[i, j, k]
        out[0] = x
        out[1] = y
        out[2] = z
    return 1


def _obstacle_kernel(tris, idx, r1, r2, origin, cell, nx, ny, ix, iy, z, offsets, climb, height,
                     blocked):  # pragma: no cover - compiled
    """:meth:`NavGrid._blocked_numpy` as loops: the same points and keys to the bit, grouped by column
    (a counting sort) and searched column by column, instead of one sort of every key and a search of
    all of them (a 500 m2 house samples 5.1e6 points; that sort and the (N, 3, 3) gathers were most of
    the array code's 2.5 s). A node is blocked when a key of a column within reach lies in its band
    [lo, hi): what the array code's two searches count. Writes ``blocked`` and returns
    1, or returns -1 where the array code must decide: no point on the grid, or a node whose height
    band is not well inside its column's run of keys (then a key of a neighbouring column could fall in
    it, which the array code's one sorted array would count and a per-column search would not)."""
    n = idx.shape[0]
    colid = np.empty(n, np.int64)
    pz = np.empty(n)
    m = 0
    for i in range(n):
        a = r1[i]
        b = r2[i]
        t = idx[i]
        wa = 1 - a
        wb = a * (1 - b)
        wc = a * b
        x = wa * tris[t, 0, 0] + wb * tris[t, 1, 0] + wc * tris[t, 2, 0]
        y = wa * tris[t, 0, 1] + wb * tris[t, 1, 1] + wc * tris[t, 2, 1]
        cx = np.int64(np.floor((x - origin[0]) / cell))
        cy = np.int64(np.floor((y - origin[1]) / cell))
        if cx >= 0 and cx < nx and cy >= 0 and cy < ny:
            colid[m] = cx * ny + cy
            pz[m] = wa * tris[t, 0, 2] + wb * tris[t, 1, 2] + wc * tris[t, 2, 2]
            m += 1
    if m == 0:
        return -1
    lo_z = pz[0]
    hi_z = pz[0]
    for i in range(1, m):
        lo_z = min(lo_z, pz[i])
        hi_z = max(hi_z, pz[i])
    zmin = lo_z - 1.0
    span = hi_z - zmin + 10.0
    # A column's keys lie in [c span + 1, c span + span - 10]: a node's band [lo, hi) within
    # (c span - 9, c span + span) meets no other column's keys (rounding is ~1e-9 m here).
    for q in range(z.shape[0]):
        if not ((z[q] + climb) - zmin > -9.0 and (z[q] + height) - zmin < span):
            return -1
    start = np.zeros(nx * ny + 1, np.int64)
    for i in range(m):
        start[colid[i] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    keys = np.empty(m)
    for i in range(m):
        c = colid[i]
        keys[fill[c]] = c * span + (pz[i] - zmin)
        fill[c] += 1
    for q in range(z.shape[0]):
        lo_rel = (z[q] + climb) - zmin
        hi_rel = (z[q] + height) - zmin
        for o in range(offsets.shape[0]):
            jx = ix[q] + offsets[o, 0]
            jy = iy[q] + offsets[o, 1]
            if jx < 0 or jx >= nx or jy < 0 or jy >= ny:
                continue
            c = jx * ny + jy
            s0 = start[c]
            s1 = start[c + 1]
            if s0 == s1:
                continue
            col = np.float64(c)
            lo = col * span + lo_rel
            hi = col * span + hi_rel
            hit = False
            for i in range(s0, s1):  # a column holds a few hundred points at most: a scan, no sort
                if lo <= keys[i] and keys[i] < hi:
                    hit = True
                    break
            if hit:
                blocked[q] = True
                break
    return 1


_JIT_LOCK = threading.Lock()
_JIT: dict | None = None  # name -> the compiled kernel (None without numba), made on first use


def _compiled(name: str):
    """Kernel ``name`` ("walk", "obstacles") as numba's dispatcher (compiled on its first call, kept in
    numba's disk cache), or None without numba. numba itself is imported here, on first use, not with
    the module: it is ~0.4 s of CPU at the start of every process that imports libs.world (the
    evaluation CLI) and never builds a grid or walks."""
    global _JIT
    if _JIT is None:
        with _JIT_LOCK:
            if _JIT is None:
                from shared.jit import AVAILABLE, kernel, numba, one_signature

                kernels = {"walk": None, "obstacles": None}
                if AVAILABLE:
                    global _nearest_level  # the kernel calls it: numba resolves the global when it compiles
                    _nearest_level = kernel()(_nearest_level)
                    jit = kernel(error_model="numpy")
                    # The obstacle pass gets its node columns as strided views (np.nonzero's), a caller
                    # with fresh arrays (the kernel's own test) as contiguous ones: two machine codes of the
                    # same kernel, 0.6-1 s of CPU each on a cold cache, where one signature does for both.
                    kernels = {"walk": jit(_walk_kernel), "obstacles": one_signature(jit(_obstacle_kernel))}
                _JIT = kernels
    return _JIT[name]
