"""Procedural multi-room houses: seeded, deterministic, labelled.

The floor plan is a binary space partition of a rectangle into rooms; rooms get types by size and
shape (the largest is the living room, the smallest a bathroom, long narrow ones hallways), doors
join rooms along a random spanning tree of the adjacency graph plus a few extra edges, so every
room is reachable. Each room has its own wall colour and a labelled floor ("kitchen floor"), so a
camera that sees the floor knows the room. Furniture is built from boxes and cylinders with class
labels and named colours ("green plant", "red sofa"), placed against walls or in the middle of the
room, and rejected when it would cut the room's free floor in two or block a doorway. With
``floors=2`` or ``3`` a straight staircase (rise < 0.2 m) in a stairwell beside the house joins each
pair of consecutive storeys; the flights alternate between the +x and the -x side of the house.

Spec string: ``generated:<seed>[:floors=<1|2|3>][:area=<m2>]`` (area of the whole house, 40-1,200 m2).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from shared.schemas import Pose

from .errors import SceneFormatError
from .furniture import ROOM_FURNITURE, chair_parts, colour_rgb, furniture_item
from .mesh_builder import MeshBuilder
from .scene import GENERATED_PREFIX, Room, Scene, SceneObject, register_scene_builder

log = logging.getLogger(__name__)

WALL_T = 0.05  # each room owns a 5 cm skin on its side of a wall: 10 cm between rooms
CEILING_H = 2.6
SLAB_T = 0.2
STOREY_H = CEILING_H + SLAB_T  # 2.8 m floor to floor
DOOR_W = 0.95
DOOR_H = 2.1
JAMB = 0.04
STAIR_W = 1.3
RASTER = 0.05
AGENT_R = 0.1
# Furniture keep-out for the connectivity check: the radius plus a cell, because the navigation
# grid blocks cells conservatively (any obstacle point within radius + half a cell diagonal).
INFLATE = AGENT_R + RASTER
EPS = 1e-6
MAX_FLOORS = 3
MIN_STAIR_DEPTH_M = 7.0
MIN_AREA_M2, MAX_AREA_M2 = 40.0, 1200.0

WALL_PAINT = {
    "living room": (0.93, 0.88, 0.74),
    "kitchen": (0.80, 0.90, 0.80),
    "bathroom": (0.74, 0.86, 0.93),
    "bedroom": (0.88, 0.78, 0.86),
    "office": (0.84, 0.84, 0.90),
    "dining room": (0.95, 0.82, 0.68),
    "hallway": (0.86, 0.86, 0.80),
    "staircase": (0.82, 0.80, 0.76),
}
FLOOR_PAINT = {
    "living room": (0.55, 0.38, 0.22),
    "kitchen": (0.78, 0.76, 0.70),
    "bathroom": (0.62, 0.72, 0.78),
    "bedroom": (0.66, 0.50, 0.36),
    "office": (0.42, 0.44, 0.50),
    "dining room": (0.60, 0.42, 0.26),
    "hallway": (0.58, 0.56, 0.50),
    "staircase": (0.50, 0.46, 0.42),
}
CEILING_COLOUR = (0.96, 0.96, 0.95)
FRAME_COLOUR = (0.36, 0.24, 0.14)
STAIR_COLOUR = (0.55, 0.40, 0.28)

GROUND_TYPES = ["living room", "kitchen", "dining room", "office", "bedroom", "bedroom", "office", "dining room"]
SINGLE_TYPES = ["living room", "kitchen", "bedroom", "dining room", "office", "bedroom", "bathroom", "bedroom", "office"]
UPPER_TYPES = ["bedroom", "office", "bedroom", "bedroom", "office", "living room"]


@dataclass(frozen=True)
class HouseSpec:
    """Parameters of a procedural house."""

    seed: int = 0
    floors: int = 1
    area_m2: float = 200.0

    def __post_init__(self) -> None:
        if not 1 <= self.floors <= MAX_FLOORS:
            raise SceneFormatError(f"floors must be 1 to {MAX_FLOORS}, got {self.floors}")
        if not MIN_AREA_M2 <= self.area_m2 <= MAX_AREA_M2:
            raise SceneFormatError(f"area must be within {MIN_AREA_M2:g}-{MAX_AREA_M2:g} m2, got {self.area_m2}")

    @classmethod
    def parse(cls, spec: str) -> HouseSpec:
        if not spec.startswith(GENERATED_PREFIX):
            raise SceneFormatError(f"not a generated scene spec: {spec!r}")
        parts = spec[len(GENERATED_PREFIX):].split(":")
        try:
            seed = int(parts[0])
            kw: dict = {}
            for p in parts[1:]:
                k, v = p.split("=", 1)
                if k == "floors":
                    kw["floors"] = int(v)
                elif k == "area":
                    kw["area_m2"] = float(v)
                else:
                    raise ValueError(f"unknown option {k!r}")
        except ValueError as exc:
            raise SceneFormatError(
                f"bad scene spec {spec!r} ({exc}); expected generated:<seed>[:floors=N][:area=M2]"
            ) from None
        return cls(seed=seed, **kw)

    @property
    def spec(self) -> str:
        s = f"{GENERATED_PREFIX}{self.seed}"
        if self.floors != 1:
            s += f":floors={self.floors}"
        if self.area_m2 != 200.0:
            s += f":area={self.area_m2:g}"
        return s


# --- floor plan ----------------------------------------------------------------------------------


@dataclass
class _Door:
    axis: int  # 0: the wall is the line x = coord; 1: the line y = coord
    coord: float
    lo: float
    hi: float
    floor: int


def _bsp(rng: np.random.Generator, lo, hi, min_side: float, max_area: float, out: list) -> None:
    w, d = hi[0] - lo[0], hi[1] - lo[1]
    area = w * d
    target = rng.uniform(0.45, 1.0) * max_area
    if area <= target or max(w, d) < 2 * min_side:
        out.append((tuple(lo), tuple(hi)))
        return
    axis = 0 if (w > d or (w == d and rng.random() < 0.5)) else 1
    length = hi[axis] - lo[axis]
    if length < 2 * min_side:
        axis = 1 - axis
        length = hi[axis] - lo[axis]
    # Occasionally carve a narrow strip: that is where hallways come from.
    if rng.random() < 0.25 and length > 2 * min_side + 1.6:
        cut = lo[axis] + (1.6 if rng.random() < 0.5 else length - 1.6)
    else:
        cut = lo[axis] + rng.uniform(min_side, length - min_side)
    cut = round(cut * 20) / 20  # on the 5 cm raster
    a_hi = list(hi)
    a_hi[axis] = cut
    b_lo = list(lo)
    b_lo[axis] = cut
    _bsp(rng, list(lo), a_hi, min_side, max_area, out)
    _bsp(rng, b_lo, list(hi), min_side, max_area, out)


def _shared_edge(a: Room, b: Room):
    """(axis, coord, lo, hi) of the wall line two rooms on one floor share, or None."""
    for axis in (0, 1):
        o = 1 - axis
        for r1, r2 in ((a, b), (b, a)):
            if abs(r1.max_xy_m[axis] - r2.min_xy_m[axis]) < EPS:
                lo = max(r1.min_xy_m[o], r2.min_xy_m[o])
                hi = min(r1.max_xy_m[o], r2.max_xy_m[o])
                if hi - lo > 0:
                    return axis, r1.max_xy_m[axis], lo, hi
    return None


def _assign_types(rng: np.random.Generator, rects: list, floor: int, want: list[str]) -> list[str]:
    areas = np.array([(h[0] - l[0]) * (h[1] - l[1]) for l, h in rects])
    short = np.array([min(h[0] - l[0], h[1] - l[1]) for l, h in rects])
    long_ = np.array([max(h[0] - l[0], h[1] - l[1]) for l, h in rects])
    types = [""] * len(rects)
    order = np.argsort(-areas, kind="stable")
    hall = [i for i in range(len(rects)) if short[i] <= 2.0 and long_[i] / short[i] >= 2.2]
    for i in hall[:2]:
        types[i] = "hallway"
    free = [i for i in order if not types[i]]
    if free:
        types[free[-1]] = "bathroom"  # the smallest room
    free = [i for i in order if not types[i]]
    wanted = list(want)
    for i in free:
        types[i] = wanted.pop(0) if wanted else str(rng.choice(["bedroom", "office"]))
    return types


def _name_rooms(types: list[str], floors: list[int], existing: dict[str, int]) -> list[str]:
    names = []
    for t in types:
        existing[t] = existing.get(t, 0) + 1
        names.append(t if existing[t] == 1 else f"{t} {existing[t]}")
    return names




class _RoomRaster:
    """Free floor of one room at 5 cm, inflated by the agent radius, to keep furniture from cutting it."""

    def __init__(self, room: Room, doors: list[_Door]):
        self.room = room
        self.lo = np.array(room.min_xy_m)
        n = np.round((np.array(room.max_xy_m) - self.lo) / RASTER).astype(int)
        self.shape = (int(n[0]), int(n[1]))
        self.free = np.ones(self.shape, dtype=bool)
        margin = WALL_T + AGENT_R + 0.02
        self._block_rect(self.lo, np.array(room.max_xy_m), inverse_margin=margin)
        self.door_zone = np.zeros(self.shape, dtype=bool)
        self.reserved = np.zeros(self.shape, dtype=bool)
        for door in doors:
            lo, hi = np.zeros(2), np.zeros(2)
            o = 1 - door.axis
            lo[o], hi[o] = door.lo + JAMB + AGENT_R, door.hi - JAMB - AGENT_R
            lo[door.axis], hi[door.axis] = door.coord - 0.9, door.coord + 0.9
            self.door_zone |= self._mask(lo, hi)
            lo[o], hi[o] = door.lo - 0.3, door.hi + 0.3
            self.reserved |= self._mask(lo, hi)
        self.door_zone &= self.free

    def _mask(self, lo, hi) -> np.ndarray:
        m = np.zeros(self.shape, dtype=bool)
        i0 = np.clip(np.floor((lo - self.lo) / RASTER + 1e-6).astype(int), 0, self.shape)
        i1 = np.clip(np.ceil((hi - self.lo) / RASTER - 1e-6).astype(int), 0, self.shape)
        m[i0[0] : i1[0], i0[1] : i1[1]] = True
        return m

    def _block_rect(self, lo, hi, inverse_margin: float) -> None:
        inner = self._mask(lo + inverse_margin, hi - inverse_margin)
        self.free &= inner

    def footprint_ok(self, lo, hi) -> bool:
        """Inside the room, off the door zones, and not a second free-floor component."""
        m = self._mask(lo, hi)
        if not m.any() or (m & self.reserved).any():
            return False
        inflated = self._mask(lo - INFLATE, hi + INFLATE)
        trial = self.free & ~inflated
        if (self.door_zone & ~trial).any():
            return False
        from scipy import ndimage  # here, not at module level: scipy.ndimage is ~0.4 s at every process start

        _, n = ndimage.label(trial)
        return n == 1

    def commit(self, lo, hi) -> None:
        self.free &= ~self._mask(lo - INFLATE, hi + INFLATE)


def _place(rng, room: Room, raster: _RoomRaster, kind: str):
    label, colour, w, d, h, parts, placement = furniture_item(kind, rng)
    lo_r = np.array(room.min_xy_m) + WALL_T
    hi_r = np.array(room.max_xy_m) - WALL_T
    for _ in range(30):
        if placement in ("wall", "on wall"):
            side = int(rng.integers(4))
            facing = [np.array([0.0, 1.0]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), np.array([-1.0, 0.0])][side]
            along = 0 if side < 2 else 1
            span_lo, span_hi = lo_r[along] + w / 2 + 0.02, hi_r[along] - w / 2 - 0.02
            if span_hi < span_lo:
                continue
            origin = np.zeros(2)
            origin[along] = rng.uniform(span_lo, span_hi)
            origin[1 - along] = [lo_r[1], hi_r[1], lo_r[0], hi_r[0]][side] + facing[1 - along] * 0.01
        else:
            facing = [np.array([0.0, 1.0]), np.array([1.0, 0.0])][int(rng.integers(2))]
            c = (lo_r + hi_r) / 2 + rng.uniform(-0.25, 0.25, 2) * (hi_r - lo_r - max(w, d))
            origin = c - facing * d / 2
        right = np.array([facing[1], -facing[0]])
        corners = np.array([origin + sx * right * w / 2 + sy * facing * d for sx in (-1, 1) for sy in (0, 1)])
        flo, fhi = corners.min(axis=0), corners.max(axis=0)
        if np.any(flo < lo_r - 1e-6) or np.any(fhi > hi_r + 1e-6):
            continue
        # Wall decorations hang within the agent's height, so they narrow the floor like furniture.
        if label != "rug" and not raster.footprint_ok(flo, fhi):
            continue
        if label != "rug":  # flat: the agent walks over it
            raster.commit(flo, fhi)
        return label, colour, origin, facing, right, (w, d, h), parts, (flo, fhi)
    return None


def _emit_parts(mb: MeshBuilder, parts, origin, facing, right, z0: float) -> None:
    for p in parts:
        if p[0] == "box":
            _, a, b, col, lab = p
            pts = []
            for x in (a[0], b[0]):
                for y in (a[1], b[1]):
                    pts.append(origin + x * right + y * facing)
            pts = np.array(pts)
            lo = np.array([*pts.min(axis=0), z0 + a[2]])
            hi = np.array([*pts.max(axis=0), z0 + b[2]])
            mb.box(lo, hi, col, lab)
        else:
            _, (x, y), r, za, zb, col, lab, rt = p
            c = origin + x * right + y * facing
            mb.cylinder(c, r, z0 + za, z0 + zb, col, lab, radius_top=rt)


# --- the house -----------------------------------------------------------------------------------


def generate_house(spec: HouseSpec | str = HouseSpec()) -> Scene:
    """Build a procedural house; the same spec always gives the same scene, to the bit."""
    if isinstance(spec, str):
        spec = HouseSpec.parse(spec)
    for attempt in range(50):
        rng = np.random.default_rng([spec.seed, attempt, spec.floors, int(spec.area_m2 * 10)])
        try:
            scene = _try_house(spec, rng)
        except _Retry as exc:
            log.debug("house %s attempt %d rejected: %s", spec.spec, attempt, exc)
            continue
        return scene
    raise SceneFormatError(f"could not generate a valid house for {spec.spec}")


register_scene_builder(GENERATED_PREFIX, generate_house)


class _Retry(Exception):
    pass


def _try_house(spec: HouseSpec, rng: np.random.Generator) -> Scene:
    floor_area = spec.area_m2 / spec.floors
    aspect = rng.uniform(0.75, 1.33)
    # A stairwell needs a floor 7 m deep. A storey too small for that at any drawn aspect (a
    # 100 m2 house on three floors) is made exactly that deep, with fewer rooms and room types.
    tiny = spec.floors > 1 and floor_area < MIN_STAIR_DEPTH_M**2 * 0.75
    if tiny:
        aspect = floor_area / MIN_STAIR_DEPTH_M**2
    W = round(math.sqrt(floor_area * aspect) * 20) / 20
    D = round(floor_area / W * 20) / 20
    if spec.floors > 1 and D < MIN_STAIR_DEPTH_M:
        raise _Retry("too shallow for a staircase")
    rooms: list[Room] = []
    doors: list[_Door] = []
    counts: dict[str, int] = {}
    for fl in range(spec.floors):
        rects: list = []
        _bsp(rng, [0.0, 0.0], [W, D], min_side=2.8, max_area=rng.uniform(30.0, 44.0), out=rects)
        if len(rects) < (4 if spec.floors == 1 else 2 if tiny else 3):
            raise _Retry("too few rooms")
        types = _assign_types(rng, rects, fl, SINGLE_TYPES if spec.floors == 1 else (GROUND_TYPES if fl == 0 else UPPER_TYPES))
        if fl == 0 and spec.floors == 1 and "kitchen" not in types:
            raise _Retry("no kitchen")
        names = _name_rooms(types, [fl] * len(types), counts)
        fl_rooms = [
            Room(n, t, fl, (float(l[0]), float(l[1])), (float(h[0]), float(h[1])), fl * STOREY_H)
            for n, t, (l, h) in zip(names, types, rects)
        ]
        doors += _doors_for(rng, fl_rooms, fl)
        rooms += fl_rooms
    rooms, doors, flights = _add_stairwells(rng, rooms, doors, W, D, spec.floors)
    shafts = {f.shaft.name: f for f in flights}
    if len({r.room_type for r in rooms if r.room_type != "staircase"}) < (3 if tiny else 4):
        raise _Retry("too few room types")

    mb = MeshBuilder()
    # Fix label ids of the structural classes first, so they are stable across seeds.
    for lab in ("wall", "door frame", "ceiling"):
        mb.label(lab)
    objects: list[SceneObject] = []
    start = None
    for room in rooms:
        if room.room_type == "staircase":
            if room.name in shafts:  # a landing is the top of a flight its shaft already built
                _emit_stairwell(mb, shafts[room.name])
            continue
        rdoors = [d for d in doors if _door_on_room(d, room)]
        _emit_room(mb, room, rdoors)
        raster = _RoomRaster(room, rdoors)
        wanted = list(ROOM_FURNITURE[room.room_type])
        # Essentials first (they define the room), then a random subset of the rest.
        essentials, extras = wanted[:2], wanted[2:]
        rng.shuffle(extras)
        n_extra = int(rng.integers(1, len(extras) + 1)) if extras else 0
        for kind in essentials + extras[:n_extra]:
            placed = _place(rng, room, raster, kind)
            if placed is None:
                continue
            label, colour, origin, facing, right, size, parts, (flo, fhi) = placed
            _emit_parts(mb, parts, origin, facing, right, room.floor_z_m)
            if kind in ("dining table", "kitchen table", "table"):
                _chairs_around(rng, mb, room, raster, flo, fhi, objects)
            centre = (flo + fhi) / 2
            objects.append(
                SceneObject(len(objects), label, colour, room.name, (float(centre[0]), float(centre[1]), room.floor_z_m),
                            (float(fhi[0] - flo[0]), float(fhi[1] - flo[1]), float(size[2])), float(math.atan2(facing[1], facing[0])))
            )
        if room.room_type == "living room" and room.floor == 0 and start is None:
            free = np.argwhere(raster.free)
            if len(free):
                c = (np.array(room.max_xy_m) - np.array(room.min_xy_m)) / 2 / RASTER
                k = free[np.argmin(np.sum((free - c) ** 2, axis=1))]
                xy = raster.lo + (k + 0.5) * RASTER
                start = Pose(position_m=(float(xy[0]), float(xy[1]), 0.0), heading_rad=float(rng.uniform(-math.pi, math.pi)))
    if len(objects) < 15:
        raise _Retry(f"only {len(objects)} objects")
    if start is None:
        raise _Retry("no free start in the living room")
    v, t, c, lab, names = mb.build()
    return Scene(
        name=spec.spec,
        vertices=v,
        triangles=t,
        vertex_colors=c,
        triangle_labels=lab,
        label_names=names,
        rooms=rooms,
        objects=objects,
        start_pose=start,
        source=spec.spec,
        floors=spec.floors,
        consistent_winding=True,
    )


def _chairs_around(rng, mb, room, raster, flo, fhi, objects) -> None:
    """Chairs facing a table on its long sides, where they fit."""
    long_axis = 0 if fhi[0] - flo[0] >= fhi[1] - flo[1] else 1
    length = fhi[long_axis] - flo[long_axis]
    n = 2 if length < 1.4 else 3
    col = str(rng.choice(["brown", "black", "white", "red", "blue"]))
    for side in (0, 1):
        for k in range(n):
            if rng.random() < 0.3:
                continue
            pos = np.zeros(2)
            pos[long_axis] = flo[long_axis] + (k + 0.5) * length / n
            facing = np.zeros(2)
            # Chair "wall" side is its back, so facing points towards the table.
            if side == 0:
                pos[1 - long_axis] = flo[1 - long_axis] - 0.5
                facing[1 - long_axis] = 1.0
            else:
                pos[1 - long_axis] = fhi[1 - long_axis] + 0.5
                facing[1 - long_axis] = -1.0
            right = np.array([facing[1], -facing[0]])
            w = d = 0.45
            origin = pos
            corners = np.array([origin + sx * right * w / 2 + sy * facing * d for sx in (-1, 1) for sy in (0, 1)])
            clo, chi = corners.min(axis=0), corners.max(axis=0)
            if not raster.footprint_ok(clo, chi):
                continue
            raster.commit(clo, chi)
            parts = chair_parts(w, d, colour_rgb(col))
            _emit_parts(mb, parts, origin, facing, right, room.floor_z_m)
            centre = (clo + chi) / 2
            objects.append(SceneObject(len(objects), "chair", col, room.name, (float(centre[0]), float(centre[1]), room.floor_z_m), (w, d, 0.9), float(math.atan2(facing[1], facing[0]))))


def _doors_for(rng, rooms: list[Room], floor: int) -> list[_Door]:
    import networkx as nx  # here, not at module level: a third of a second at every process start

    g = nx.Graph()
    g.add_nodes_from(range(len(rooms)))
    edges = {}
    for i in range(len(rooms)):
        for j in range(i + 1, len(rooms)):
            e = _shared_edge(rooms[i], rooms[j])
            if e is not None and e[3] - e[2] >= DOOR_W + 0.5:
                edges[(i, j)] = e
                g.add_edge(i, j, weight=float(rng.random()))
    if not nx.is_connected(g):
        raise _Retry("rooms not connected")
    tree = nx.minimum_spanning_tree(g, weight="weight")
    chosen = set(tree.edges())
    for e in sorted(g.edges()):
        if e not in chosen and (e[1], e[0]) not in chosen and rng.random() < 0.25:
            chosen.add(e)
    out = []
    for i, j in sorted(tuple(sorted(e)) for e in chosen):
        axis, coord, lo, hi = edges[(i, j)]
        s = rng.uniform(lo + 0.25, hi - 0.25 - DOOR_W)
        s = round(s * 20) / 20
        out.append(_Door(axis, coord, s, s + DOOR_W, floor))
    return out


@dataclass(frozen=True)
class _Flight:
    """A straight flight between storeys ``shaft.floor`` and ``shaft.floor + 1``."""

    shaft: Room  # the stairwell, a room of the lower floor; it builds all the geometry
    landing: Room  # its top, a room of the upper floor's plan (no geometry of its own)
    doors: tuple[_Door, _Door]  # the bottom door (lower floor) and the top door (upper floor)


def _add_stairwells(rng, rooms: list[Room], doors: list[_Door], W: float, D: float, floors: int):
    """One stairwell per pair of consecutive floors, outside the +x wall, then the -x wall, in turn.

    Each has a door at the bottom (its lower floor) and at the top (the next floor up). Alternating
    sides keeps every flight against the house wall of both storeys it joins.
    """
    flights: list[_Flight] = []
    for k in range(floors - 1):
        flight = _add_stairwell(rng, rooms, k, W, D, plus_x=(k % 2 == 0))
        flights.append(flight)
        rooms = rooms + [flight.shaft, flight.landing]
        doors = doors + list(flight.doors)
    return rooms, doors, flights


def _add_stairwell(rng, rooms: list[Room], lower: int, W: float, D: float, plus_x: bool) -> _Flight:
    n_steps = int(math.ceil(STOREY_H / 0.19))
    tread = 0.27
    run = n_steps * tread  # the last step is the upper landing's edge
    length = 1.0 + run + 1.1
    wall_x = W if plus_x else 0.0
    on_wall = (lambda r: abs(r.max_xy_m[0] - W) < EPS) if plus_x else (lambda r: abs(r.min_xy_m[0]) < EPS)
    for y0 in rng.permutation(np.arange(0.0, D - length + 1e-6, 0.05)):
        y0 = float(round(y0 * 20) / 20)
        bottom = (y0 + 0.08, y0 + 0.08 + DOOR_W)
        top = (y0 + length - 0.08 - DOOR_W, y0 + length - 0.08)
        r0 = [r for r in rooms if r.floor == lower and on_wall(r) and r.min_xy_m[1] + 0.25 <= bottom[0] and bottom[1] <= r.max_xy_m[1] - 0.25]
        r1 = [r for r in rooms if r.floor == lower + 1 and on_wall(r) and r.min_xy_m[1] + 0.25 <= top[0] and top[1] <= r.max_xy_m[1] - 0.25]
        if r0 and r1:
            break
    else:
        raise _Retry("no place for the stairwell doors")
    x0, x1 = (W, W + STAIR_W) if plus_x else (-STAIR_W, 0.0)
    suffix = "" if lower == 0 else f" {lower + 1}"
    shaft = Room(f"staircase{suffix}", "staircase", lower, (x0, y0), (x1, y0 + length), lower * STOREY_H)
    landing = Room(f"staircase landing{suffix}", "staircase", lower + 1, (x0, y0), (x1, y0 + length),
                   (lower + 1) * STOREY_H)
    return _Flight(shaft, landing, (_Door(0, wall_x, *bottom, lower), _Door(0, wall_x, *top, lower + 1)))


def _door_on_room(d: _Door, room: Room) -> bool:
    if d.floor != room.floor:
        return False
    o = 1 - d.axis
    on_line = abs(room.min_xy_m[d.axis] - d.coord) < EPS or abs(room.max_xy_m[d.axis] - d.coord) < EPS
    return on_line and room.min_xy_m[o] - EPS <= d.lo and d.hi <= room.max_xy_m[o] + EPS


def _emit_room(mb: MeshBuilder, room: Room, doors: list[_Door]) -> None:
    lo = np.array(room.min_xy_m)
    hi = np.array(room.max_xy_m)
    z0 = room.floor_z_m
    floor_label = f"{room.room_type} floor"
    mb.box((lo[0], lo[1], z0 - SLAB_T / 2), (hi[0], hi[1], z0), FLOOR_PAINT[room.room_type], floor_label)
    mb.box((lo[0], lo[1], z0 + CEILING_H), (hi[0], hi[1], z0 + CEILING_H + SLAB_T / 2), CEILING_COLOUR, "ceiling")
    _emit_walls(mb, room, doors, z0, CEILING_H, WALL_PAINT[room.room_type])


def _emit_walls(mb, room: Room, doors: list[_Door], z0: float, height: float, paint) -> None:
    lo = np.array(room.min_xy_m)
    hi = np.array(room.max_xy_m)
    for axis in (0, 1):
        o = 1 - axis
        for coord, inward in ((lo[axis], 1.0), (hi[axis], -1.0)):
            # Door openings on this wall line, as intervals along the other axis.
            holes = sorted(
                ((d.lo, d.hi, d.floor) for d in doors if d.axis == axis and abs(d.coord - coord) < EPS),
                key=lambda h: h[0],
            )
            t0 = coord if inward > 0 else coord - WALL_T
            t1 = t0 + WALL_T
            start = lo[o]
            pieces = []
            for a, b, fl in holes:
                pieces.append((start, a))
                start = b
            pieces.append((start, hi[o]))

            def box(a_o, b_o, za, zb, col, lab):
                blo, bhi = np.zeros(3), np.zeros(3)
                blo[axis], bhi[axis] = t0, t1
                blo[o], bhi[o] = a_o, b_o
                blo[2], bhi[2] = za, zb
                mb.box(blo, bhi, col, lab)

            for a, b in pieces:
                box(a, b, z0, z0 + height, paint, "wall")
            for a, b, fl in holes:
                dz = fl * STOREY_H if room.room_type == "staircase" else z0
                if dz > z0:
                    box(a, b, z0, dz, paint, "wall")
                box(a, b, dz + DOOR_H, z0 + height, paint, "wall")
                # The frame: two jambs and a head, slightly proud of the wall.
                fl_lo, fl_hi = t0 - 0.01, t1 + 0.01
                for ja, jb in ((a, a + JAMB), (b - JAMB, b)):
                    blo, bhi = np.zeros(3), np.zeros(3)
                    blo[axis], bhi[axis] = fl_lo, fl_hi
                    blo[o], bhi[o] = ja, jb
                    blo[2], bhi[2] = dz, dz + DOOR_H
                    mb.box(blo, bhi, FRAME_COLOUR, "door frame")
                blo, bhi = np.zeros(3), np.zeros(3)
                blo[axis], bhi[axis] = fl_lo, fl_hi
                blo[o], bhi[o] = a, b
                blo[2], bhi[2] = dz + DOOR_H - JAMB, dz + DOOR_H
                mb.box(blo, bhi, FRAME_COLOUR, "door frame")


def _emit_stairwell(mb: MeshBuilder, flight: _Flight) -> None:
    room = flight.shaft
    lo = np.array(room.min_xy_m)
    hi = np.array(room.max_xy_m)
    z0 = room.floor_z_m
    n_steps = int(math.ceil(STOREY_H / 0.19))
    rise = STOREY_H / n_steps
    tread = 0.27
    y = lo[1] + 1.0
    mb.box((lo[0], lo[1], z0 - SLAB_T / 2), (hi[0], hi[1], z0), FLOOR_PAINT["staircase"], "staircase floor")
    for k in range(1, n_steps + 1):
        y_end = y + tread if k < n_steps else hi[1]
        label = "stairs" if k < n_steps else "staircase floor"
        col = STAIR_COLOUR if k < n_steps else FLOOR_PAINT["staircase"]
        mb.box((lo[0], y, z0), (hi[0], y_end, z0 + k * rise), col, label)
        y = y_end
    top = z0 + STOREY_H + CEILING_H
    mb.box((lo[0], lo[1], top), (hi[0], hi[1], top + SLAB_T / 2), CEILING_COLOUR, "ceiling")
    _emit_walls(mb, room, list(flight.doors), z0, top - z0, WALL_PAINT["staircase"])
