"""The spatial scene graph of a map version (issue 32): rooms, objects, stairs and navigation graphs.

Built from what the robot recorded - the map's labelled points and the exploration's navigation graph
(and the mapper's regions on its nodes) - never from a simulator's scene description. A map without
labels still gets a geometric graph: rooms from the mapper's regions (unnamed), their openings, and
the free-space lattice. The builder is :mod:`libs.scenegraph`; the map store keeps one graph per map
version beside the cloud; ``MAP_SCENE_GRAPH`` serves it on the bus, ``GET /maps/{id}/scene-graph.json``
over HTTP.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from shared.arrays import Array

from .base import Count, Distance_m, Message, SEQ_LIMIT, SegmentId, Xyz_m
from .navigation import NavGraph

# Limits of one graph: a 1,000 m2 three-floor house has ~40 rooms and ~300 objects; these leave two
# orders of magnitude for scans while refusing a payload that would only be a mistake.
SCENE_GRAPH_MAX_ROOMS = 10_000
SCENE_GRAPH_MAX_OBJECTS = 100_000
SCENE_GRAPH_MAX_POLYGON = 4_096  # vertices of one room footprint
SCENE_GRAPH_MAX_NAV_NODES = 500_000
SCENE_GRAPH_MAX_GRID_CELLS = 16_000_000  # one floor's raster (4 km2 at 0.5 m, 1 km2 at 0.25 m)

Area_m2 = Annotated[float, Field(ge=0.0, le=1e8)]
Share = Annotated[float, Field(ge=0.0, le=1.0)]
Xy_m = tuple[Annotated[float, Field(ge=-2.0e7, le=2.0e7)], Annotated[float, Field(ge=-2.0e7, le=2.0e7)]]
Size_m = tuple[Distance_m, Distance_m, Distance_m]
Rgb = tuple[Annotated[int, Field(ge=0, le=255)], Annotated[int, Field(ge=0, le=255)],
            Annotated[int, Field(ge=0, le=255)]]
FloorIndex = Annotated[int, Field(ge=-100, le=100)]


class SceneOpening(Message):
    """A door or opening between two rooms: where the free space of one meets the other's."""

    a: str
    b: str
    position_m: Xyz_m
    width_m: Distance_m = 0.0


class SceneRoom(Message):
    """One room instance: two bedrooms are two rooms of ``room_type`` "bedroom"; ``room_type`` is ""
    on a geometric graph (a map without labels)."""

    room_id: str = Field(min_length=1, max_length=64)
    room_type: str = Field("", max_length=64)
    floor: FloorIndex = 0
    floor_z_m: float = Field(0.0, ge=-2.0e7, le=2.0e7)
    centroid_m: Xyz_m
    area_m2: Area_m2
    footprint_m: list[Xy_m] = Field(default_factory=list, max_length=SCENE_GRAPH_MAX_POLYGON,
                                    description="outline polygon (counter-clockwise) of the room's floor")
    neighbours: list[str] = Field(default_factory=list, description="room ids it opens onto")
    region: int | None = Field(None, ge=-1, le=100_000, description="the mapper's region, when known")


class SceneObject(Message):
    """One object instance seen in the map."""

    object_id: str = Field(min_length=1, max_length=64)
    label: str = Field(min_length=1, max_length=128)
    colour: str = Field("", max_length=32)
    colour_rgb: Rgb = (0, 0, 0)
    position_m: Xyz_m
    size_m: Size_m
    room_id: str | None = None
    points: Count = 0
    # Where to stand to see it: in front of the side its points were seen from (the cloud's view
    # directions); None when the map does not record them. A goal "next to" it is here, not behind a wall.
    approach_m: Xyz_m | None = None


class SceneStairs(Message):
    """A stairway between two floors."""

    stairs_id: str = Field(min_length=1, max_length=64)
    from_floor: FloorIndex
    to_floor: FloorIndex
    bottom_m: Xyz_m
    top_m: Xyz_m


class FloorGrid(Message):
    """One floor's walkable cells as a raster: cell (i, j) covers x in origin_x + [i, i+1) * cell_m and y in
    origin_y + [j, j+1) * cell_m. ``cells``: 0 blocked or unseen, 1 free floor, 2 stairs (walkable, and
    joined to the same cell of the next floor up)."""

    floor: FloorIndex
    z_m: float = Field(ge=-2.0e7, le=2.0e7)
    origin_m: Xy_m
    cell_m: float = Field(gt=0.01, le=10.0)
    cells: Array("uint8", 2)
    # Which room each cell belongs to: an index into SceneGraph.rooms, -1 for none (same shape as cells).
    rooms: Array("int16", 2) | None = None

    @model_validator(mode="after")
    def _sized(self):
        if self.cells.size > SCENE_GRAPH_MAX_GRID_CELLS:
            raise ValueError(f"cells: {self.cells.size} cells, at most {SCENE_GRAPH_MAX_GRID_CELLS}")
        if self.cells.size and int(self.cells.max()) > 2:
            raise ValueError("cells: values are 0 (blocked), 1 (free) or 2 (stairs)")
        if self.rooms is not None and (self.rooms.shape != self.cells.shape or
                                       (self.rooms.size and int(self.rooms.min()) < -1)):
            raise ValueError("rooms: one room index (or -1) per cell, the shape of cells")
        return self


class SceneGraph(Message):
    """The whole graph of one map version (see the module docstring)."""

    map_id: str = ""
    version: int = Field(0, ge=0, le=SEQ_LIMIT)
    labelled: bool = False  # rooms and objects carry names (the map had semantic labels)
    floors_z_m: list[Annotated[float, Field(ge=-2.0e7, le=2.0e7)]] = Field(default_factory=list, max_length=200)
    rooms: list[SceneRoom] = Field(default_factory=list, max_length=SCENE_GRAPH_MAX_ROOMS)
    openings: list[SceneOpening] = Field(default_factory=list, max_length=SCENE_GRAPH_MAX_ROOMS * 8)
    objects: list[SceneObject] = Field(default_factory=list, max_length=SCENE_GRAPH_MAX_OBJECTS)
    stairs: list[SceneStairs] = Field(default_factory=list, max_length=SCENE_GRAPH_MAX_ROOMS)
    navigation: NavGraph = Field(default_factory=lambda: NavGraph(nodes=[], edges=[]),
                                 description="the exploration's navigation graph (empty when the map was imported)")
    free_space: list[FloorGrid] = Field(default_factory=list, max_length=200,
                                        description="each floor's walkable cells (routes are planned on them)")
    build_s: float = Field(0.0, ge=0.0, le=1e6)

    @model_validator(mode="after")
    def _references_resolve(self):
        ids = {r.room_id for r in self.rooms}
        if len(ids) != len(self.rooms):
            raise ValueError("room ids must be unique")
        for o in self.openings:
            if o.a not in ids or o.b not in ids:
                raise ValueError(f"opening {o.a}-{o.b} names a room the graph does not have")
        for r in self.rooms:
            if bad := [n for n in r.neighbours if n not in ids]:
                raise ValueError(f"room {r.room_id} neighbours unknown rooms {bad}")
        for o in self.objects:
            if o.room_id is not None and o.room_id not in ids:
                raise ValueError(f"object {o.object_id} is in unknown room {o.room_id}")
        if len(self.navigation.nodes) > SCENE_GRAPH_MAX_NAV_NODES:
            raise ValueError(f"navigation: {len(self.navigation.nodes)} nodes, at most {SCENE_GRAPH_MAX_NAV_NODES}")
        return self

    def room(self, room_id: str) -> SceneRoom | None:
        return next((r for r in self.rooms if r.room_id == room_id), None)


class SceneGraphRequest(Message):
    """``MAP_SCENE_GRAPH``: the scene graph of a map version (latest when ``version`` is None)."""

    map_id: SegmentId
    version: int | None = Field(None, ge=1, le=SEQ_LIMIT)
