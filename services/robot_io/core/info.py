"""``SceneInfo``: what a robot knows about its world, as a typed, JSON-friendly message.

It derives from the bus ``Message`` base, so the adapter can send it as it is; ``model_dump()`` gives
plain dicts and lists (label ids become JSON object keys as strings only in ``model_dump_json``).
"""

from __future__ import annotations

from pydantic import Field

from shared.schemas import Message, Pose

from .navgrid import NavGrid
from .scene import Room, Scene, SceneObject


class RoomInfo(Message):
    """A labelled room: an axis-aligned box on the floor of storey ``floor``."""

    name: str  # unique: "bedroom", "bedroom 2", ...
    room_type: str
    floor: int = Field(ge=0)
    min_xy_m: tuple[float, float]
    max_xy_m: tuple[float, float]
    floor_z_m: float
    area_m2: float = Field(ge=0.0)

    @classmethod
    def from_room(cls, r: Room) -> RoomInfo:
        return cls(name=r.name, room_type=r.room_type, floor=r.floor, min_xy_m=r.min_xy_m, max_xy_m=r.max_xy_m,
                   floor_z_m=r.floor_z_m, area_m2=r.area_m2)


class ObjectInfo(Message):
    """A labelled object (furniture) with its footprint box."""

    object_id: int = Field(ge=0)
    label: str
    colour: str
    description: str  # "green plant": how instructions name it
    room: str
    position_m: tuple[float, float, float]  # centre of the footprint, on the floor
    size_m: tuple[float, float, float]  # extent along world x, y, z
    yaw_rad: float

    @classmethod
    def from_object(cls, o: SceneObject) -> ObjectInfo:
        return cls(object_id=o.object_id, label=o.label, colour=o.colour, description=o.description, room=o.room,
                   position_m=o.position_m, size_m=o.size_m, yaw_rad=o.yaw_rad)


class SceneInfo(Message):
    """A scene's name, extent, rooms, objects, semantic label names and walkable area."""

    name: str
    source: str
    floors: int = Field(ge=1)
    bounds_min_m: tuple[float, float, float]
    bounds_max_m: tuple[float, float, float]
    triangle_count: int = Field(ge=0)
    label_names: dict[int, str]  # semantic id -> class name; -1 (unknown) is not listed
    rooms: list[RoomInfo]
    objects: list[ObjectInfo]
    reachable_area_m2: float = Field(ge=0.0)  # of the agent's main walkable region
    nav_cell_m: float = Field(gt=0.0)
    start_pose: Pose | None = None

    @classmethod
    def from_scene(cls, scene: Scene, nav: NavGrid) -> SceneInfo:
        lo, hi = scene.bounds_m
        return cls(
            name=scene.name,
            source=scene.source,
            floors=scene.floors,
            bounds_min_m=tuple(float(v) for v in lo),
            bounds_max_m=tuple(float(v) for v in hi),
            triangle_count=len(scene.triangles),
            label_names={int(k): v for k, v in scene.label_names.items()},
            rooms=[RoomInfo.from_room(r) for r in scene.rooms],
            objects=[ObjectInfo.from_object(o) for o in scene.objects],
            reachable_area_m2=nav.reachable_area_m2,
            nav_cell_m=nav.cell_m,
            start_pose=scene.start_pose,
        )

    def room(self, name: str) -> RoomInfo:
        for r in self.rooms:
            if r.name == name:
                return r
        raise KeyError(name)
