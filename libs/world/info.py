"""A simulated scene described as the system's one scene schema (:class:`shared.schemas.SceneSummary`).

The simulator knows its rooms, objects, labels and walkable area exactly; :func:`describe_scene` says
so in the shared schema, which the robot port returns and robot-io sends as it is.
"""

from __future__ import annotations

from shared.schemas import ObjectInfo, RoomInfo, SceneSummary

from .navgrid import NavGrid
from .scene import Scene


def describe_scene(scene: Scene, nav: NavGrid) -> SceneSummary:
    """Every room reaches from its floor up to the storey above (the scene's top on the last storey)."""
    lo, hi = scene.bounds_m
    top_z = float(hi[2])
    storey_z = sorted({float(r.floor_z_m) for r in scene.rooms})

    def ceiling(floor_z: float) -> float:
        above = [z for z in storey_z if z > floor_z + 1e-6]
        return above[0] if above else max(top_z, floor_z)

    rooms = [RoomInfo(name=r.name, room_type=r.room_type, floor=r.floor,
                      bounds_min_m=(r.min_xy_m[0], r.min_xy_m[1], r.floor_z_m),
                      bounds_max_m=(r.max_xy_m[0], r.max_xy_m[1], ceiling(r.floor_z_m)), area_m2=r.area_m2)
             for r in scene.rooms]
    objects = [ObjectInfo(object_id=o.object_id, label=o.label, colour=o.colour, description=o.description,
                          room=o.room, position_m=o.position_m, size_m=o.size_m, yaw_rad=o.yaw_rad)
               for o in scene.objects]
    return SceneSummary(
        scene=scene.name, source=scene.source, floors=scene.floors,
        bounds_min_m=tuple(float(v) for v in lo), bounds_max_m=tuple(float(v) for v in hi),
        triangle_count=len(scene.triangles), reachable_area_m2=nav.reachable_area_m2, nav_cell_m=nav.cell_m,
        label_names={int(k): v for k, v in scene.label_names.items()}, rooms=rooms, objects=objects,
        start_pose=scene.start_pose,
    )
