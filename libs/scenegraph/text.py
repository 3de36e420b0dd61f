"""A compact text form of a scene graph, for an MLLM policy's prompt (issue 32).

One line per room: its display name, floor, area, the objects it holds and the rooms it opens onto,
then the stairs, then where the agent stands. Rooms of one type are numbered ("bedroom 1", "bedroom 2")
so that the model can tell instances apart; a geometric graph (no labels) names rooms "room 3".

The text has a size bound: rooms are listed nearest the agent first (hops through openings, then
distance), and when the bound is reached the rest are left out and the text says how many - the
model should know the list is partial rather than believe the house ends there.
"""

from __future__ import annotations

from collections import Counter, deque

import numpy as np

from shared.scene_names import room_names  # noqa: F401 - one naming rule for every surface
from shared.schemas import SceneGraph, SceneRoom

# Objects listed per room: a room with 40 chairs and plates says "14 more objects" after this many kinds.
MAX_OBJECT_KINDS_PER_ROOM = 8
# Below this an agent "on floor k" is really below floor k (the highest floor at most this below it).
_FLOOR_TOLERANCE_M = 0.8


def floor_index_of(graph: SceneGraph, xyz) -> int | None:
    """Index (into ``floors_z_m``, else ``free_space``) of the floor a point stands on: the highest floor
    at most 0.8 m above it (a pose's z may be the floor's or a little below it)."""
    zs = list(graph.floors_z_m) or [g.z_m for g in graph.free_space]
    if not zs:
        return None
    below = [k for k, z in enumerate(zs) if z <= float(xyz[2]) + _FLOOR_TOLERANCE_M]
    return below[-1] if below else 0


def room_at(graph: SceneGraph, xyz) -> SceneRoom | None:
    """The room under a point: the floor raster's room cell when the graph has one, else the nearest
    room centroid on that floor (within 1.5x the room's equivalent radius)."""
    f = floor_index_of(graph, xyz)  # None: the graph records no floors, every room is a candidate
    grids = [g for g in graph.free_space if g.rooms is not None]
    if grids and f is not None:
        g = min(grids, key=lambda g: abs(g.z_m - (graph.floors_z_m[f] if f < len(graph.floors_z_m) else xyz[2])))
        i = int((float(xyz[0]) - g.origin_m[0]) // g.cell_m)
        j = int((float(xyz[1]) - g.origin_m[1]) // g.cell_m)
        if 0 <= i < g.rooms.shape[0] and 0 <= j < g.rooms.shape[1]:
            k = int(g.rooms[i, j])
            if 0 <= k < len(graph.rooms):
                return graph.rooms[k]
    same = [r for r in graph.rooms if f is None or r.floor == f] or list(graph.rooms)
    if not same:
        return None
    p = np.asarray(xyz[:2], float)
    best = min(same, key=lambda r: float(np.hypot(*(np.asarray(r.centroid_m[:2]) - p))))
    reach = 1.5 * float(np.sqrt(max(best.area_m2, 1.0) / np.pi))
    return best if float(np.hypot(*(np.asarray(best.centroid_m[:2]) - p))) <= reach else None


def _order_from(graph: SceneGraph, start: SceneRoom | None, xyz) -> list[SceneRoom]:
    """Rooms nearest the agent first: hops through openings from its room, ties (and unreachable rooms)
    by straight-line distance."""
    by_id = {r.room_id: r for r in graph.rooms}
    hops: dict[str, int] = {}
    if start is not None:
        hops[start.room_id] = 0
        queue = deque([start.room_id])
        while queue:
            rid = queue.popleft()
            for n in by_id[rid].neighbours:
                if n not in hops:
                    hops[n] = hops[rid] + 1
                    queue.append(n)
    p = np.asarray(xyz, float) if xyz is not None else None

    def key(r: SceneRoom):
        d = 0.0 if p is None else float(np.linalg.norm(np.asarray(r.centroid_m) - p))
        return (hops.get(r.room_id, 10**6), d, r.room_id)

    return sorted(graph.rooms, key=key)


def _objects_phrase(graph: SceneGraph, room_id: str) -> str:
    kinds = Counter()
    for o in graph.objects:
        if o.room_id == room_id:
            kinds[f"{o.colour} {o.label}".strip()] += 1
    if not kinds:
        return "no objects seen"
    listed = kinds.most_common(MAX_OBJECT_KINDS_PER_ROOM)
    words = [name if n == 1 else f"{n} x {name}" for name, n in listed]
    rest = sum(kinds.values()) - sum(n for _, n in listed)
    if rest:
        words.append(f"{rest} more objects")
    return ", ".join(words)


def scene_graph_text(graph: SceneGraph, agent_xyz=None, max_chars: int = 4000) -> str:
    """The graph as prompt text of at most ``max_chars`` characters (see the module docstring).

    ``agent_xyz``: the agent's position (world frame, z-up metres); None leaves out where it is."""
    if max_chars < 200:
        raise ValueError(f"max_chars must be >= 200 to say anything useful, got {max_chars}")
    names = room_names(graph)
    floors = len(graph.floors_z_m) or len(graph.free_space) or 1
    here = room_at(graph, agent_xyz) if agent_xyz is not None else None
    head = [f"Map of the building (scene graph from the pre-exploration): {len(graph.rooms)} rooms on "
            f"{floors} floor{'s' if floors != 1 else ''}, {len(graph.objects)} objects"
            + ("" if graph.labelled else "; rooms are unnamed (the map has no labels)") + "."]
    if agent_xyz is not None:
        f = floor_index_of(graph, agent_xyz)
        name = names[here.room_id] if here is not None else ""
        where = ("outside every mapped room" if here is None else
                 f"in {name}" if not here.room_type else f"in the {name}")
        head.append(f"You are {where}, on floor {0 if f is None else f} (floors are numbered from 0, the lowest).")
    tail: list[str] = []
    if graph.stairs:
        tail.append("Stairs: " + "; ".join(f"floor {s.from_floor} to floor {s.to_floor}" for s in graph.stairs) + ".")
    budget = max_chars - sum(len(s) + 1 for s in head + tail) - len("Rooms (name | floor | area | objects | opens onto):") - 1
    lines: list[str] = []
    ordered = _order_from(graph, here, agent_xyz)
    omitted = 0
    for k, r in enumerate(ordered):
        neighbours = ", ".join(names[n] for n in r.neighbours) or "no openings seen"
        line = (f"- {names[r.room_id]}{' (you are here)' if here is r else ''} | floor {r.floor} | "
                f"{r.area_m2:.0f} m2 | {_objects_phrase(graph, r.room_id)} | {neighbours}")
        # Leave room for the note that says how many rooms were left out.
        note = len(f"(... {len(ordered) - k} more rooms, farther from you, left out: the map is large)") + 1
        if len(line) + 1 + (note if k + 1 < len(ordered) else 0) > budget:
            omitted = len(ordered) - k
            break
        lines.append(line)
        budget -= len(line) + 1
    if omitted:
        lines.append(f"(... {omitted} more rooms, farther from you, left out: the map is large)")
    text = "\n".join(head + ["Rooms (name | floor | area | objects | opens onto):"] + lines + tail)
    return text[:max_chars]


def floor_room_labels(graph: SceneGraph, xyz) -> list[tuple[str, float, float]]:
    """(display name, x, y) of every room on the floor a point stands on: what a top-down map of that
    floor should name, with the same names as the text form ("bedroom 2")."""
    names = room_names(graph)
    f = floor_index_of(graph, xyz)
    return [(names[r.room_id], float(r.centroid_m[0]), float(r.centroid_m[1]))
            for r in graph.rooms if f is None or r.floor == f]
