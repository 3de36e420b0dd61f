"""Build a :class:`shared.schemas.SceneGraph` from what the robot recorded (issue 32).

Inputs are the map's cloud (its labelled points: room floors are named like ``"kitchen floor"``, objects
by class) and, when the map came from an exploration, the exploration's navigation graph (its nodes carry
the mapper's regions and floors). Never the simulator's scene description: the rooms and objects here
are what the map shows, with the map's errors.

Per floor: a raster of the floor at ``cell_m`` - floor points near the floor's height, minus cells where
something stands between the ankles and the head (walls, furniture) - is the walkable space. Rooms are
connected components of one room-floor label (two bedrooms are two rooms); on a map without labels the
regions of the exploration's nodes split the floor instead (rooms without names), and without those
every connected piece of floor is a room. Openings are where the cells of two rooms touch. Objects are
3-D connected components of one label's voxels.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, cKDTree

from shared.cloud import PointCloud
from shared.schemas import (
    FloorGrid, NavGraph, SceneGraph, SceneObject, SceneOpening, SceneRoom, SceneStairs,
)

log = logging.getLogger(__name__)

# Label names that are structure, not objects (matched as words of the label name).
_STRUCTURE = ("wall", "ceiling", "floor", "door", "window", "stair", "railing", "beam", "column")
# Dominant colour names: a small palette of reference colours (sRGB 0-1), matched on hue and lightness.
# Data, not code: a map's colours are shaded, so the match is on the chroma direction and lightness.
PALETTE: dict[str, tuple[float, float, float]] = {
    "red": (0.78, 0.16, 0.14), "green": (0.20, 0.62, 0.22), "blue": (0.18, 0.32, 0.78),
    "yellow": (0.92, 0.80, 0.18), "orange": (0.93, 0.50, 0.12), "purple": (0.52, 0.26, 0.66),
    "pink": (0.92, 0.55, 0.68), "white": (0.93, 0.93, 0.91), "black": (0.10, 0.10, 0.11),
    "grey": (0.50, 0.51, 0.53), "brown": (0.48, 0.31, 0.17), "beige": (0.85, 0.77, 0.60),
    "silver": (0.75, 0.77, 0.80), "teal": (0.10, 0.55, 0.55),
}


@dataclass
class SceneGraphConfig:
    """How the graph is cut out of the cloud."""

    cell_m: float = 0.25  # raster of the walkable floor
    floor_band_m: float = 0.15  # a floor point lies within this of its floor's height
    body_low_m: float = 0.2  # something between these heights above the floor blocks a cell
    body_high_m: float = 1.6
    min_floor_share: float = 0.02  # of the floor points, for a height to be a floor
    min_floor_gap_m: float = 1.5  # two floors are at least this far apart
    min_room_m2: float = 1.0  # smaller pieces of a room label are noise (or seen through a door)
    door_erode_m: float = 0.5  # same-type rooms are split where their floor is narrower than twice this
    object_voxel_m: float = 0.15
    min_object_points: int = 30
    min_opening_cells: int = 2
    approach_gap_m: float = 0.6  # an object's approach point is this far out from its seen side
    min_walk_island_m2: float = 1.0  # smaller pieces of walkable floor are dropped


def _words(name: str) -> list[str]:
    return name.lower().replace("_", " ").replace("-", " ").split()


def is_floor_label(name: str) -> bool:
    return "floor" in _words(name)


def room_type_of(name: str) -> str:
    """'kitchen floor' -> 'kitchen'."""
    return " ".join(w for w in _words(name) if w != "floor")


def is_structure(name: str) -> bool:
    words = _words(name)
    return any(w.startswith(s) for w in words for s in _STRUCTURE)


_PALETTE_NAMES = list(PALETTE)
_PALETTE_RGB = np.array([PALETTE[k] for k in _PALETTE_NAMES])
_PALETTE_DIR = _PALETTE_RGB / (np.linalg.norm(_PALETTE_RGB, axis=1, keepdims=True) + 1e-6)


def colour_name(rgb: np.ndarray) -> str:
    """Nearest palette colour of a (shaded) sRGB 0-255 colour."""
    c = np.asarray(rgb, float) / 255.0
    # Shading scales a colour: compare directions (chroma) and, less, the lightness. One array expression
    # for the whole palette (a loop over it was a third of a 1,000 m2 map's build).
    d = np.linalg.norm(c / (np.linalg.norm(c) + 1e-6) - _PALETTE_DIR, axis=1) + 0.35 * np.abs(
        float(c.mean()) - _PALETTE_RGB.mean(axis=1))
    return _PALETTE_NAMES[int(np.argmin(d))]


def _floor_heights(z: np.ndarray, cfg: SceneGraphConfig, nav: NavGraph | None) -> list[float]:
    """Floor heights: peaks of the floor points' heights (or the navigation graph's node heights)."""
    if len(z) == 0:
        if nav is not None and nav.nodes:
            z = np.array([n.position_m[2] for n in nav.nodes])
        else:
            return [0.0]
    bins = np.round(z / 0.1).astype(np.int64)
    vals, counts = np.unique(bins, return_counts=True)
    order = np.argsort(-counts)
    floors: list[float] = []
    for i in order:
        if counts[i] < cfg.min_floor_share * len(z):
            break
        h = float(vals[i]) * 0.1
        if all(abs(h - f) >= cfg.min_floor_gap_m for f in floors):
            floors.append(h)
    return sorted(floors) or [float(np.median(z))]


def build_scene_graph(cloud: PointCloud, navigation: NavGraph | None = None,
                      config: SceneGraphConfig | None = None, map_id: str = "", version: int = 0) -> SceneGraph:
    """The scene graph of ``cloud`` (see the module docstring)."""
    cfg = config or SceneGraphConfig()
    t0 = time.perf_counter()
    xyz = np.asarray(cloud.xyz, np.float64)
    labels = cloud.labels if cloud.labels is not None and cloud.label_names else None
    names = {int(k): v for k, v in (cloud.label_names or {}).items()} if labels is not None else {}
    floor_ids = np.array([k for k, v in names.items() if is_floor_label(v)], np.int64)
    stair_ids = np.array([k for k, v in names.items() if any(w.startswith("stair") for w in _words(v))], np.int64)
    object_ids = [k for k, v in names.items() if not is_structure(v)]
    wall_ids = np.array([k for k, v in names.items() if any(w.startswith(("wall", "door")) for w in _words(v))],
                        np.int64)
    is_floor_pt = np.isin(labels, floor_ids) if labels is not None and floor_ids.size else None
    is_wall_pt = np.isin(labels, wall_ids) if labels is not None and wall_ids.size else None
    labelled = bool(floor_ids.size)

    # Floors: from the labelled floor points, else the lowest dense heights of the whole cloud.
    fz = xyz[is_floor_pt, 2] if is_floor_pt is not None else (
        np.array([n.position_m[2] for n in navigation.nodes]) if navigation is not None and navigation.nodes
        else xyz[xyz[:, 2] <= np.percentile(xyz[:, 2], 20), 2])
    floors = _floor_heights(fz, cfg, navigation)

    lo = xyz[:, :2].min(axis=0) - cfg.cell_m
    hi = xyz[:, :2].max(axis=0) + cfg.cell_m
    shape = tuple(int(v) for v in np.ceil((hi - lo) / cfg.cell_m).astype(int) + 1)
    ij = np.floor((xyz[:, :2] - lo) / cfg.cell_m).astype(np.int64)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    stair_pt = np.isin(labels, stair_ids) if labels is not None and stair_ids.size else np.zeros(len(xyz), bool)

    nav_xyz = nav_region = None
    if navigation is not None and navigation.nodes:
        nav_xyz = np.array([n.position_m for n in navigation.nodes], np.float64)
        nav_region = np.array([-1 if n.region is None else n.region for n in navigation.nodes], np.int64)

    rooms: list[SceneRoom] = []
    openings: list[SceneOpening] = []
    grids: list[FloorGrid] = []
    room_rasters: list[np.ndarray] = []  # per floor: room index per cell (-1 none)
    counters: dict[str, int] = {}
    for fi, z0 in enumerate(floors):
        dz = xyz[:, 2] - z0
        near_floor = np.abs(dz) <= cfg.floor_band_m
        if is_floor_pt is not None:
            near_floor &= is_floor_pt | stair_pt
        body = (dz > cfg.body_low_m) & (dz < cfg.body_high_m) & ~stair_pt
        floor_cells = np.zeros(shape[0] * shape[1], bool)
        floor_cells[flat[near_floor]] = True
        blocked = np.zeros_like(floor_cells)
        blocked[flat[body]] = True
        floor_cells = ndimage.binary_closing(floor_cells.reshape(shape), iterations=1) | floor_cells.reshape(shape)
        blocked = blocked.reshape(shape)
        walls = np.zeros(shape[0] * shape[1], bool)
        if is_wall_pt is not None:
            walls[flat[body & is_wall_pt]] = True
        walls = walls.reshape(shape)
        free = floor_cells & ~blocked
        # Stairs: cells whose stair points rise from this floor (walkable, joined to the floor above).
        stairs_cells = np.zeros(shape, bool)
        on_stairs = stair_pt & (dz > -0.3) & (dz < (floors[fi + 1] - z0 + 0.3 if fi + 1 < len(floors) else 0.3))
        if on_stairs.any():
            s = np.zeros(shape[0] * shape[1], bool)
            s[flat[on_stairs]] = True
            stairs_cells = ndimage.binary_closing(s.reshape(shape), iterations=1) | s.reshape(shape)
        cells = np.where(stairs_cells, 2, np.where(free, 1, 0)).astype(np.uint8)
        # Islands of floor (seen on top of furniture, between its legs) are no place to walk to: a goal
        # snapped onto one would be unreachable.
        comp, n = ndimage.label(cells > 0, structure=np.ones((3, 3)))
        if n > 1:
            sizes = ndimage.sum(cells > 0, comp, index=np.arange(1, n + 1))
            cells[np.isin(comp, np.flatnonzero(sizes < cfg.min_walk_island_m2 / cfg.cell_m**2) + 1)] = 0

        # Rooms of this floor.
        raster = np.full(shape, -1, np.int64)
        pieces: list[tuple[str, np.ndarray, int | None]] = []  # (room type, cell mask, region)
        min_cells = max(1, int(cfg.min_room_m2 / cfg.cell_m**2))
        if labelled:
            # The floor points of this floor once; each room label picks from those (not from all points).
            nf = np.flatnonzero(near_floor)
            nf_labels, nf_flat = labels[nf], flat[nf]
            for fid in floor_ids:
                m = np.zeros(shape[0] * shape[1], bool)
                m[nf_flat[nf_labels == fid]] = True
                m = ndimage.binary_closing(m.reshape(shape), iterations=1) | m.reshape(shape)
                # A wall is thinner than a cell: both sides' floor fills its cells, so the label alone
                # would join two rooms through it. Cells where something stands are not a room's floor.
                m = ndimage.binary_fill_holes(m & ~walls) & ~walls  # furniture in the middle is the room's
                comp, n = ndimage.label(m, structure=np.ones((3, 3)))
                sizes = ndimage.sum(m, comp, index=np.arange(1, n + 1))
                for k in np.flatnonzero(sizes >= min_cells):
                    for part in _split_at_doors(comp == k + 1, cfg, min_cells):
                        pieces.append((room_type_of(names[int(fid)]), part, None))
        elif nav_xyz is not None:
            on_floor = np.abs(nav_xyz[:, 2] - z0) < cfg.min_floor_gap_m / 2
            if on_floor.any():
                tree = cKDTree(nav_xyz[on_floor, :2])
                ci, cj = np.nonzero(floor_cells)
                centres = lo + (np.stack([ci, cj], 1) + 0.5) * cfg.cell_m
                _, near = tree.query(centres)
                reg = nav_region[on_floor][near]
                for r in np.unique(reg):
                    m = np.zeros(shape, bool)
                    m[ci[reg == r], cj[reg == r]] = True
                    comp, n = ndimage.label(m, structure=np.ones((3, 3)))
                    sizes = ndimage.sum(m, comp, index=np.arange(1, n + 1))
                    for k in np.flatnonzero(sizes >= min_cells):
                        pieces.append(("", comp == k + 1, int(r)))
        if not pieces:
            comp, n = ndimage.label(floor_cells, structure=np.ones((3, 3)))
            sizes = ndimage.sum(floor_cells, comp, index=np.arange(1, n + 1))
            pieces = [("", comp == k + 1, None) for k in np.flatnonzero(sizes >= min_cells)]
        first = len(rooms)
        for rtype, mask, region in pieces:
            key = rtype.replace(" ", "-") or "room"
            counters[key] = counters.get(key, 0) + 1
            rid = f"{key}-{counters[key]}"
            raster[mask & (raster < 0)] = len(rooms)
            ci, cj = np.nonzero(mask)
            pts = lo + (np.stack([ci, cj], 1) + 0.5) * cfg.cell_m
            rooms.append(SceneRoom(room_id=rid, room_type=rtype, floor=fi, floor_z_m=float(z0),
                                   centroid_m=(float(pts[:, 0].mean()), float(pts[:, 1].mean()), float(z0)),
                                   area_m2=float(mask.sum() * cfg.cell_m**2), footprint_m=_outline(pts, cfg.cell_m),
                                   region=region))
        # Walkable cells no room claims (doorways, thresholds) belong to the nearest room within 1 m, so
        # that the rooms on either side of a door touch there.
        if len(rooms) > first:
            walk = cells > 0
            _, (ni, nj) = ndimage.distance_transform_edt(raster < 0, return_indices=True)
            dist = ndimage.distance_transform_edt(raster < 0) * cfg.cell_m
            fill = walk & (raster < 0) & (dist <= 1.0)
            raster[fill] = raster[ni[fill], nj[fill]]
            openings += _openings(raster, walk, rooms, lo, cfg, z0)
        room_rasters.append(raster)
        grids.append(FloorGrid(floor=fi, z_m=float(z0), origin_m=(float(lo[0]), float(lo[1])), cell_m=cfg.cell_m,
                               cells=cells, rooms=raster.astype(np.int16)))

    for o in openings:
        for a, b in ((o.a, o.b), (o.b, o.a)):
            r = next(r for r in rooms if r.room_id == a)
            if b not in r.neighbours:
                r.neighbours.append(b)

    objects = _objects(xyz, cloud.rgb, labels, names, object_ids, floors, room_rasters, rooms, lo, shape, cfg,
                       cloud.view_dirs) if labels is not None else []
    stairs = _stairs(xyz, stair_pt, floors, navigation)
    return SceneGraph(map_id=map_id, version=version, labelled=labelled, floors_z_m=[float(f) for f in floors],
                      rooms=rooms, openings=openings, objects=objects, stairs=stairs,
                      navigation=navigation if navigation is not None else NavGraph(nodes=[], edges=[]),
                      free_space=grids, build_s=round(time.perf_counter() - t0, 4))


def _split_at_doors(mask: np.ndarray, cfg: SceneGraphConfig, min_cells: int) -> list[np.ndarray]:
    """Two rooms of one type joined by a door share one floor label: erode by ``door_erode_m`` (a door is
    narrower than twice that, a room wider), and give every cell to the nearest core that survived."""
    it = max(1, int(round(cfg.door_erode_m / cfg.cell_m)))
    core = ndimage.binary_erosion(mask, iterations=it)
    comp, n = ndimage.label(core, structure=np.ones((3, 3)))
    if n < 2:
        return [mask]
    sizes = ndimage.sum(core, comp, index=np.arange(1, n + 1))
    keep = np.flatnonzero(sizes >= max(1, min_cells // 4)) + 1
    if len(keep) < 2:
        return [mask]
    seeds = np.where(np.isin(comp, keep), comp, 0)
    _, (ni, nj) = ndimage.distance_transform_edt(seeds == 0, return_indices=True)
    owner = seeds[ni, nj]
    parts = [mask & (owner == k) for k in keep]
    return [p for p in parts if p.sum() >= min_cells] or [mask]


def _outline(pts: np.ndarray, cell_m: float) -> list[tuple[float, float]]:
    """The convex outline of a room's cell centres, grown by half a cell (counter-clockwise)."""
    h = cell_m / 2
    corners = np.concatenate([pts + [dx, dy] for dx in (-h, h) for dy in (-h, h)])
    try:
        hull = ConvexHull(corners)
    except Exception:  # a degenerate (one-cell wide) room: its bounding box
        a, b = corners.min(axis=0), corners.max(axis=0)
        return [(float(a[0]), float(a[1])), (float(b[0]), float(a[1])), (float(b[0]), float(b[1])),
                (float(a[0]), float(b[1]))]
    return [(float(x), float(y)) for x, y in corners[hull.vertices]]


def _openings(raster, walk, rooms, lo, cfg: SceneGraphConfig, z0: float) -> list[SceneOpening]:
    """Where walkable cells of two rooms touch (4-neighbours): one opening per pair of rooms."""
    pairs: dict[tuple[int, int], list[tuple[float, float]]] = {}
    for axis in (0, 1):
        a = raster[:-1, :] if axis == 0 else raster[:, :-1]
        b = raster[1:, :] if axis == 0 else raster[:, 1:]
        wa = walk[:-1, :] if axis == 0 else walk[:, :-1]
        wb = walk[1:, :] if axis == 0 else walk[:, 1:]
        hit = (a >= 0) & (b >= 0) & (a != b) & wa & wb
        for i, j in zip(*np.nonzero(hit)):
            ra, rb = int(a[i, j]), int(b[i, j])
            key = (min(ra, rb), max(ra, rb))
            c = lo + (np.array([i, j]) + 0.5 + (np.array([0.5, 0]) if axis == 0 else np.array([0, 0.5]))) * cfg.cell_m
            pairs.setdefault(key, []).append((float(c[0]), float(c[1])))
    out = []
    for (ra, rb), pts in sorted(pairs.items()):
        if len(pts) < cfg.min_opening_cells:
            continue
        p = np.array(pts)
        # The largest cluster of touching cells is the door; its centre is where a route crosses.
        centre = p[np.argmin(np.linalg.norm(p - p.mean(axis=0), axis=1))]
        out.append(SceneOpening(a=rooms[ra].room_id, b=rooms[rb].room_id,
                                position_m=(float(centre[0]), float(centre[1]), float(z0)),
                                width_m=float(len(pts) * cfg.cell_m)))
    return out


def _objects(xyz, rgb, labels, names, object_ids, floors, room_rasters, rooms, lo, shape, cfg,
             view_dirs=None) -> list[SceneObject]:
    out: list[SceneObject] = []
    counters: dict[str, int] = {}
    floor_arr = np.asarray(floors)
    # One sort of the labels instead of a full pass per label (a 1,000 m2 map has ~4 M points, ~40 labels);
    # the bounds of every label in one searchsorted, in the labels' own dtype (a Python int per call made
    # numpy convert the whole sorted array each time: 4.5 of 16 s).
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    ids = np.asarray(object_ids, dtype=sorted_labels.dtype)
    starts = np.searchsorted(sorted_labels, ids, "left")
    ends = np.searchsorted(sorted_labels, ids, "right")
    for lid, a0, a1 in zip(object_ids, starts, ends):
        if a1 - a0 < cfg.min_object_points:
            continue
        sel = order[a0:a1]
        p = xyz[sel]
        pmin = p.min(axis=0)
        vox = np.floor((p - pmin) / cfg.object_voxel_m).astype(np.int64)
        dims = vox.max(axis=0) + 1
        if int(np.prod(dims)) > 50_000_000:  # a label spread over a huge volume: cluster coarser
            vox //= 4
            dims = vox.max(axis=0) + 1
        grid = np.zeros(dims, bool)
        grid[vox[:, 0], vox[:, 1], vox[:, 2]] = True
        comp, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
        pc = comp[vox[:, 0], vox[:, 1], vox[:, 2]]
        counts = np.bincount(pc, minlength=n + 1)
        # The points of each component as one slice (one sort), and their boxes and direction sums in one
        # reduceat each, instead of a mask over all the label's points per component.
        by_comp = np.argsort(pc, kind="stable")
        bounds = np.r_[0, np.cumsum(counts)]
        nonempty = np.flatnonzero(counts)
        seg = bounds[nonempty]
        ps = p[by_comp]
        mins = np.minimum.reduceat(ps, seg, axis=0)
        maxs = np.maximum.reduceat(ps, seg, axis=0)
        dsum = (np.add.reduceat(np.asarray(view_dirs[sel][by_comp], np.float64), seg, axis=0)
                if view_dirs is not None else None)
        row = {int(k): r for r, k in enumerate(nonempty)}
        for k in np.flatnonzero(counts >= cfg.min_object_points):
            if k == 0:
                continue
            r = row[int(k)]
            members = sel[by_comp[bounds[k]: bounds[k + 1]]]
            a, b = mins[r], maxs[r]
            centre = (a + b) / 2
            fi = int(np.searchsorted(floor_arr, a[2] + 0.3) - 1) if len(floor_arr) else 0
            fi = min(max(fi, 0), len(room_rasters) - 1)
            room_id = None
            if room_rasters:
                i, j = np.floor((centre[:2] - lo) / cfg.cell_m).astype(int)
                if 0 <= i < shape[0] and 0 <= j < shape[1]:
                    raster = room_rasters[fi]
                    rr = raster[i, j]
                    if rr < 0:  # against a wall or over unseen floor: the nearest room cell within 1.5 m
                        win = raster[max(0, i - 6): i + 7, max(0, j - 6): j + 7]
                        ii, jj = np.nonzero(win >= 0)
                        if len(ii):
                            kk = np.argmin((ii + max(0, i - 6) - i) ** 2 + (jj + max(0, j - 6) - j) ** 2)
                            rr = win[ii[kk], jj[kk]]
                    room_id = rooms[int(rr)].room_id if rr >= 0 else None
            label = names[int(lid)]
            key = label.replace(" ", "-")
            counters[key] = counters.get(key, 0) + 1
            col = np.median(rgb[members], axis=0)
            approach = None
            if dsum is not None:
                v = dsum[r][:2] / counts[k] / 127.0
                if np.linalg.norm(v) > 0.15:
                    v /= np.linalg.norm(v)
                    reach = float(np.abs(v) @ ((b - a)[:2] / 2)) + cfg.approach_gap_m
                    approach = (float(centre[0] + v[0] * reach), float(centre[1] + v[1] * reach), float(floors[fi]))
            out.append(SceneObject(object_id=f"{key}-{counters[key]}", label=label, colour=colour_name(col),
                                   colour_rgb=tuple(int(v) for v in col), position_m=tuple(float(v) for v in centre),
                                   size_m=tuple(float(v) for v in (b - a)), room_id=room_id, points=int(counts[k]),
                                   approach_m=approach))
    return out


def _stairs(xyz, stair_pt, floors, navigation: NavGraph | None) -> list[SceneStairs]:
    out: list[SceneStairs] = []
    if stair_pt.any() and len(floors) > 1:
        p = xyz[stair_pt]
        comp_lo = p[np.argmin(p[:, 2])]
        comp_hi = p[np.argmax(p[:, 2])]
        f0 = int(np.argmin(np.abs(np.asarray(floors) - comp_lo[2])))
        f1 = int(np.argmin(np.abs(np.asarray(floors) - comp_hi[2])))
        if f1 != f0:
            out.append(SceneStairs(stairs_id="stairs-1", from_floor=f0, to_floor=f1,
                                   bottom_m=tuple(map(float, comp_lo)), top_m=tuple(map(float, comp_hi))))
    if not out and navigation is not None and navigation.stairs:
        by_id = {n.node_id: n for n in navigation.nodes}
        pts = np.array([by_id[s].position_m for s in navigation.stairs if s in by_id])
        if len(pts) >= 2 and np.ptp(pts[:, 2]) > 1.0:
            a, b = pts[np.argmin(pts[:, 2])], pts[np.argmax(pts[:, 2])]
            fa = int(np.argmin(np.abs(np.asarray(floors) - a[2])))
            fb = int(np.argmin(np.abs(np.asarray(floors) - b[2])))
            out.append(SceneStairs(stairs_id="stairs-1", from_floor=fa, to_floor=fb,
                                   bottom_m=tuple(map(float, a)), top_m=tuple(map(float, b))))
    return out
