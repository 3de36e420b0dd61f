"""Ground an instruction on the map's scene graph (issue 32): which object instance it ends at, and why.

The instruction's sub-goals (:mod:`.instruction`) name rooms in order, landmarks on the way and a final
object, often with its colour and room ("Stop next to the blue bed in the bedroom"). Every object of the
final class is a reading; each is scored by how much of the instruction it explains: its colour, its
room's type, and whether the shortest route to it from the start passes through the named rooms in the
named order (a subsequence match) and by the named landmarks. The best reading is the goal; the route
is the geodesic field towards it (:class:`libs.scenegraph.Router`).
"""

from __future__ import annotations

import math
import re
from functools import lru_cache
from dataclasses import dataclass, field

import numpy as np

from libs.scenegraph import Router
from libs.scenegraph.builder import PALETTE
from shared.schemas import SceneGraph, SceneObject, SceneRoom

from .instruction import LANDMARKS, ParsedInstruction
from .instruction import label_matches as _label_matches

# The same few (label, target) pairs are asked for every reading and path point: a regex each time was
# most of a grounding's cost (0.18 of 0.30 s on a two-floor map).
label_matches = lru_cache(maxsize=16_384)(_label_matches)


@dataclass
class Grounding:
    """The chosen reading: the goal object, where to stand, the rooms the route passes and the field."""

    # The object the instruction ends at, or the room it names when the map recorded no such object there
    # (a plant hidden behind a wardrobe is in no map; "in the bedroom" still says where the route ends).
    goal: SceneObject | SceneRoom
    goal_m: np.ndarray
    field: np.ndarray
    rooms: list[str]  # room ids along the route, in order
    explained: str
    alternatives: int
    route_m: list[np.ndarray] = field(default_factory=list)
    readings: list[tuple[float, str, str]] = field(default_factory=list)  # (score, object id, why), best first

    @property
    def goal_id(self) -> str:
        return node_id(self.goal)

    @property
    def goal_position_m(self) -> tuple[float, float, float]:
        return self.goal.position_m if isinstance(self.goal, SceneObject) else self.goal.centroid_m

    @property
    def goal_size_m(self) -> tuple[float, float, float]:
        """The object's size; a room goal is a point (its stand cell), size 0."""
        return self.goal.size_m if isinstance(self.goal, SceneObject) else (0.0, 0.0, 0.0)

    @property
    def goal_extent_m(self) -> float:
        """How far from its stand point the goal may be: 0 for an object; for a room goal its radius
        (the unseen object stands somewhere in the room, not at its centre)."""
        return 0.0 if isinstance(self.goal, SceneObject) else math.sqrt(self.goal.area_m2 / math.pi)


# A reading that stops in the named room because the map holds no object of the named class there: it
# explains the room (+3, as an object in it does) but not the object (an object of the class in that room
# scores at least +1 more for the class, and one in another room 3 + 2 less): the room wins only over
# objects of the right class in the wrong room.
ROOM_READING_PENALTY = 1.5


def _room_stand_point(graph: SceneGraph, router: Router, room_index: int) -> np.ndarray | None:
    """The walkable cell of a room nearest its centroid (the centroid of an L-shaped room may be outside it)."""
    r = graph.rooms[room_index]
    f = router.floor_of((r.centroid_m[0], r.centroid_m[1], r.floor_z_m))
    if f < 0 or graph.free_space[f].rooms is None:
        return None
    g = graph.free_space[f]
    ci, cj = np.nonzero((g.cells > 0) & (g.rooms == room_index))
    if not len(ci):
        return None
    pts = np.c_[g.origin_m[0] + (ci + 0.5) * g.cell_m, g.origin_m[1] + (cj + 0.5) * g.cell_m]
    k = int(np.argmin(np.hypot(pts[:, 0] - r.centroid_m[0], pts[:, 1] - r.centroid_m[1])))
    return np.array([pts[k, 0], pts[k, 1], g.z_m])


def node_id(node: SceneObject | SceneRoom) -> str:
    """The graph id of a reading's goal: an object's, or a room's when the room is the goal."""
    return node.object_id if isinstance(node, SceneObject) else node.room_id


class GroundingError(Exception):
    """The instruction could not be tied to the graph (no such object, no route): the policy falls back."""


def _colour_before(text: str, word_phrases: tuple[str, ...]) -> str | None:
    low = text.lower()
    for p in word_phrases:
        m = re.search(rf"\b({'|'.join(PALETTE)})\s+(?:\w+\s+)?{re.escape(p)}\b", low)
        if m:
            return m.group(1)
    return None


def _stand_point(graph: SceneGraph, router: Router, o: SceneObject, cells_of: dict | None = None) -> np.ndarray:
    """Where to stop "next to" ``o``: the walkable cell of its own room nearest its footprint (the room's
    side of the wall it stands against), else the side its points were seen from, else its centre.
    ``cells_of``: a cache of each (floor, room)'s walkable cell centres for the readings of one grounding."""
    centre = np.asarray(o.position_m, float)
    base = centre - [0.0, 0.0, o.size_m[2] / 2]
    f = router.floor_of(base)
    room_index = next((k for k, r in enumerate(graph.rooms) if r.room_id == o.room_id), None)
    if f >= 0 and room_index is not None and graph.free_space[f].rooms is not None:
        g = graph.free_space[f]
        key = (f, room_index)
        pts = None if cells_of is None else cells_of.get(key)
        if pts is None:
            ci, cj = np.nonzero((g.cells > 0) & (g.rooms == room_index))
            pts = np.c_[g.origin_m[0] + (ci + 0.5) * g.cell_m, g.origin_m[1] + (cj + 0.5) * g.cell_m]
            if cells_of is not None:
                cells_of[key] = pts
        if len(pts):
            d = np.maximum(np.abs(pts - centre[:2]) - np.asarray(o.size_m[:2]) / 2, 0.0)
            dist = np.hypot(d[:, 0], d[:, 1])
            k = int(np.argmin(dist))
            if dist[k] <= 1.5:
                return np.array([pts[k, 0], pts[k, 1], g.z_m])
    if o.approach_m is not None:
        return np.asarray(o.approach_m, float)
    return centre


def _subsequence_hits(wanted: list[str], seen: list[str]) -> int:
    """How many of ``wanted`` appear in ``seen`` in order (greedy)."""
    k = 0
    for s in seen:
        if k < len(wanted) and label_matches(s, wanted[k]):
            k += 1
    return k


def _turns_at_rooms(parsed: ParsedInstruction) -> list[tuple[int, float]]:
    """(index of the room entered, 0 for the start; expected turn in rad) for each clause with a turn."""
    # A turn clause ("turn left") is split from the room clause it leads into ("go through the office").
    out, k, pending = [], 0, None
    for sg in parsed.subgoals:
        turn = sg.turn if sg.turn is not None else pending
        if sg.rooms and not sg.stop:
            if sg.leave:
                if turn is not None:
                    out.append((0, turn.angle_rad))
            else:
                k += 1
                if turn is not None:
                    out.append((k, turn.angle_rad))
            pending = None
        elif sg.turn is not None:
            pending = sg.turn
    return out


def _turn_agreement(turns, path, rooms_at, start_heading_rad) -> int:
    """+1 per turn of the instruction that the route makes where it says, -1 per one it does not.
    ``rooms_at``: the room id (or None) of each point of ``path``."""
    if not turns or len(path) < 3:
        return 0
    pts = np.asarray(path)
    entry = [0]
    for i in range(1, len(rooms_at)):
        if rooms_at[i] is not None and rooms_at[i] != rooms_at[i - 1] and rooms_at[i] not in [
                rooms_at[j] for j in entry]:
            entry.append(i)
    score = 0
    for k, want in turns:
        if k >= len(entry):
            continue
        i = entry[k]
        if i == 0:
            d = pts[min(2, len(pts) - 1)] - pts[0]
            before = start_heading_rad
        else:
            b = pts[i] - pts[max(0, i - 1)]
            d = pts[min(i + 2, len(pts) - 1)] - pts[i]
            before = math.atan2(b[1], b[0])
        if np.hypot(d[0], d[1]) < 1e-6:
            continue
        got = math.remainder(math.atan2(d[1], d[0]) - before, 2 * math.pi)
        score += 1 if abs(math.remainder(got - want, 2 * math.pi)) < math.radians(50) else -1
    return score


def ground(parsed: ParsedInstruction, graph: SceneGraph, router: Router, start_m: np.ndarray,
           start_heading_rad: float = 0.0) -> Grounding:
    if not graph.objects:
        raise GroundingError("the map's scene graph has no objects (a map without labels)")
    if not parsed.subgoals:
        raise GroundingError("the instruction has no parsable clause")
    stop_sg = next((sg for sg in parsed.subgoals if sg.stop), parsed.subgoals[-1])
    # The map's own object classes are vocabulary too: "the brown nightstand" names a class the parser's
    # table does not know, and without this the last landmark named anywhere (a bookshelf passed) won.
    known = sorted({o.label.lower() for o in graph.objects}, key=len, reverse=True)
    own = next((lab for lab in known if re.search(rf"\b{re.escape(lab)}s?\b", stop_sg.text.lower())), None)
    final = stop_sg.landmarks or parsed.final_landmarks
    if own is not None and not any(label_matches(own, t) for t in stop_sg.landmarks):
        target = own
        candidates = [o for o in graph.objects if o.label.lower() == own]
    else:
        if not final:
            raise GroundingError("the instruction names no final landmark")
        target = final[-1]
        candidates = [o for o in graph.objects if label_matches(o.label, target)]
    final_room = stop_sg.rooms[-1] if stop_sg.rooms else None
    if not candidates and final_room is None:
        raise GroundingError(f"no {target!r} in the map's scene graph")
    colour = _colour_before(stop_sg.text, LANDMARKS.get(target, (target,)))
    # The rooms the route should pass in order (rooms being left are where it starts); the stop clause's
    # room is the one entered last ("enter the office ... stop next to the desk in the office").
    wanted_rooms = [r for sg in parsed.subgoals if sg is not stop_sg or not any(
        s2.rooms for s2 in parsed.subgoals if s2 is not stop_sg) for r in sg.rooms]
    literal = next((p for p in sorted(LANDMARKS.get(target, (target,)), key=len, reverse=True)
                    if re.search(rf"\b{re.escape(p)}\b", stop_sg.text.lower())), target)
    turns = _turns_at_rooms(parsed)
    passed_marks = [m for sg in parsed.subgoals if not sg.stop for m in sg.landmarks]
    rooms_by_id = {r.room_id: r for r in graph.rooms}
    mark_xy = {m: np.array([x.position_m[:2] for x in graph.objects if label_matches(x.label, m)]).reshape(-1, 2)
               for m in passed_marks}
    # One Dijkstra from the start answers every reading: its distance and (descending this field from the
    # reading's stand point) its route. Only the chosen reading gets its own field, the one followed.
    from_start = router.field(start_m, snap_m=1.0)
    if from_start is None:
        raise GroundingError("the robot's start is off the map's walkable space")
    cells_of: dict = {}
    room_ids = [r.room_id for r in graph.rooms]

    def route_reading(stand: np.ndarray):
        """(score, rooms passed, path, why) of the route from the start to ``stand``; None if unreachable."""
        nodes = router.path_nodes(from_start, stand, snap_m=2.0)[::-1]  # start -> stand
        if not nodes:
            return None
        d = float(from_start[nodes[-1]])
        if not math.isfinite(d):
            return None
        score, why = 0.0, []
        sampled = nodes[::2] + ([nodes[-1]] if (len(nodes) - 1) % 2 else [])
        path = list(router.positions(sampled))
        seen_rooms: list[str] = []
        for k in router.node_room[nodes]:
            if k >= 0 and (not seen_rooms or seen_rooms[-1] != room_ids[k]):
                seen_rooms.append(room_ids[k])
        types = [rooms_by_id[r].room_type for r in seen_rooms]
        hits = _subsequence_hits(wanted_rooms, types)
        score += 1.0 * hits - 0.5 * (len(wanted_rooms) - hits)
        rooms_at = [room_ids[k] if k >= 0 else None for k in router.node_room[sampled]]
        agree = _turn_agreement(turns, path, rooms_at, start_heading_rad)
        score += 0.7 * agree
        if turns:
            why.append(f"turns {agree:+d}")
        if passed_marks and path:
            pts = np.array(path)
            for m in passed_marks:
                xy = mark_xy[m]
                near = len(xy) and float(np.min(np.linalg.norm(pts[:, None, :2] - xy[None], axis=2))) < 2.0
                score += 0.7 if near else -0.3
        score -= 0.01 * d  # between equal readings, the nearer
        why.append(f"route passes {hits}/{len(wanted_rooms)} named rooms in order, {d:.1f} m")
        return score, seen_rooms, path, why

    scored = []
    in_named_room = False
    for o in candidates:
        if o.points < 20:
            continue
        stand = _stand_point(graph, router, o, cells_of)
        route = route_reading(stand)
        if route is None:
            continue
        score, why = 0.0, []
        if re.search(rf"\b{re.escape(literal)}\b", o.label.lower()):
            score += 1.0  # "cabinet" names a cabinet before a wardrobe (one canonical class)
        if colour is not None:
            ok = o.colour == colour
            score += 1.0 if ok else 0.0
            why.append(f"{o.colour}{'' if ok else ' (not ' + colour + ')'}")
        room = rooms_by_id.get(o.room_id) if o.room_id else None
        if final_room is not None and room is not None:
            ok = label_matches(room.room_type, final_room)
            in_named_room |= ok
            score += 3.0 if ok else -2.0
            why.append(f"in {room.room_id}" + ("" if ok else f" (not a {final_room})"))
        scored.append((score + route[0], o, stand, route[1], route[2], ", ".join(why + route[3])))
    if final_room is not None and not in_named_room:
        # No object of the class was recorded in a room of the named type: the room itself is a reading
        # (which of the same-named rooms, the route's order, turns and landmarks decide, as for objects).
        for k, r in enumerate(graph.rooms):
            if not r.room_type or not label_matches(r.room_type, final_room):
                continue
            stand = _room_stand_point(graph, router, k)
            route = None if stand is None else route_reading(stand)
            if route is None:
                continue
            why = [f"{r.room_id}, no {target} recorded in a {final_room}"]
            scored.append((3.0 - ROOM_READING_PENALTY + route[0], r, stand, route[1], route[2],
                           ", ".join(why + route[3])))
    if not scored:
        raise GroundingError(f"no {target!r} of the map is reachable on its walkable space")
    scored.sort(key=lambda s: -s[0])
    best = scored[0]
    goal_node_m = best[2]
    fld = router.field(goal_node_m)
    best_id = node_id(best[1])
    if fld is None:
        raise GroundingError(f"{best_id} is off the map's walkable space")
    return Grounding(goal=best[1], goal_m=goal_node_m, field=fld, rooms=best[3],
                     explained=f"{best_id}: {best[5]}", alternatives=len(scored) - 1, route_m=best[4],
                     readings=[(round(x[0], 2), node_id(x[1]), x[5]) for x in scored])
