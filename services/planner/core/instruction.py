"""Instruction parsing for the offline heuristic policy.

An R2R-style instruction ("Walk past the sofa, turn left into the kitchen and stop next to the fridge.")
is split into ordered sub-goals, each with an optional turn, distance, rooms and landmarks. Vocabulary
and synonyms cover the rooms and objects of indoor scenes (the generated houses and Matterport3D).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import StrEnum


class Turn(StrEnum):
    LEFT = "left"
    RIGHT = "right"
    SLIGHT_LEFT = "slight_left"
    SLIGHT_RIGHT = "slight_right"
    AROUND = "around"
    STRAIGHT = "straight"

    @property
    def angle_rad(self) -> float:
        """Expected change of direction, positive = left (the agent convention)."""
        return {
            Turn.LEFT: math.pi / 2,
            Turn.RIGHT: -math.pi / 2,
            Turn.SLIGHT_LEFT: math.pi / 4,
            Turn.SLIGHT_RIGHT: -math.pi / 4,
            Turn.AROUND: math.pi,
            Turn.STRAIGHT: 0.0,
        }[self]


# canonical name -> phrases that mean it (longest phrases are matched first)
ROOMS: dict[str, tuple[str, ...]] = {
    "living room": ("living room", "livingroom", "lounge", "family room", "sitting room", "den"),
    "bedroom": ("bedroom", "bed room", "master bedroom", "guest room", "nursery"),
    "kitchen": ("kitchen", "kitchenette"),
    "bathroom": ("bathroom", "restroom", "washroom", "toilet room", "powder room", "bath room"),
    "hallway": ("hallway", "hall", "corridor", "entryway", "foyer", "landing", "passage"),
    "office": ("office", "study", "workroom"),
    "dining room": ("dining room", "dining area"),
    "laundry room": ("laundry room", "laundry", "utility room"),
    "closet": ("closet", "walk-in"),
    "garage": ("garage",),
}
LANDMARKS: dict[str, tuple[str, ...]] = {
    "bed": ("bed", "beds"),
    "sofa": ("sofa", "sofas", "couch", "couches", "loveseat", "settee"),
    "table": ("table", "tables", "dining table", "coffee table", "kitchen table", "counter", "countertop", "island"),
    "chair": ("chair", "chairs", "armchair", "stool", "stools", "seat"),
    "fridge": ("fridge", "refrigerator", "freezer"),
    "oven": ("oven", "stove", "cooker", "microwave"),
    "sink": ("sink", "sinks", "basin", "washbasin"),
    "toilet": ("toilet", "toilets", "commode"),
    "bathtub": ("bathtub", "bath tub", "tub", "shower"),
    "desk": ("desk", "desks", "workstation"),
    "bookshelf": ("bookshelf", "bookshelves", "bookcase", "shelf", "shelves", "shelving"),
    "plant": ("plant", "plants", "potted plant", "flowers", "tree"),
    "tv": ("tv", "television", "tv stand", "monitor", "screen"),
    "wardrobe": ("wardrobe", "dresser", "cabinet", "cupboard", "armoire", "chest of drawers"),
    "stairs": ("stairs", "staircase", "stairway", "stair"),  # not "steps": a distance unit
    "door": ("door", "doors", "doorway", "door frame", "entrance", "exit", "archway"),
    "rug": ("rug", "carpet", "mat"),
    "lamp": ("lamp", "lamps", "light"),
    "window": ("window", "windows"),
    "picture": ("picture", "painting", "photo", "poster", "mirror"),
    "fireplace": ("fireplace",),
}

_NUMBERS = {
    "a": 1, "one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8,
    "nine": 9, "ten": 10, "few": 3, "couple": 2, "several": 4, "half": 0.5,
}
_STEP_LENGTH_M = 0.75  # one human "step"
_DISTANCE = re.compile(
    r"\b(\d+(?:\.\d+)?|a|one|two|three|four|five|six|seven|eight|nine|ten|few|couple|several|half)"
    r"(?:\s+of)?\s*(?:a\s+)?(m|meters?|metres?|feet|foot|ft|steps?|paces?|yards?)\b"
)
_LEAVE = re.compile(r"\b(exit|exits|leave|leaving|out of)\b")
_STOP = re.compile(r"\b(stop|wait|halt|you(?:'re| are) done)\b")
_CLAUSE_SPLIT = re.compile(r"[.;!?]|,|\band then\b|\bthen\b|\bafter that\b|\bonce\b|\buntil\b|\band\b")


def _phrase_index(vocab: dict[str, tuple[str, ...]]) -> list[tuple[re.Pattern, str]]:
    pairs = [(p, canon) for canon, phrases in vocab.items() for p in phrases]
    pairs.sort(key=lambda pc: -len(pc[0]))  # "dining table" before "table"
    return [(re.compile(rf"\b{re.escape(p)}\b"), canon) for p, canon in pairs]


_ROOM_PATTERNS = _phrase_index(ROOMS)
_LANDMARK_PATTERNS = _phrase_index(LANDMARKS)


def _find_ordered(text: str, patterns: list[tuple[re.Pattern, str]]) -> list[str]:
    """Canonical names in order of appearance; a matched span is consumed so 'dining room' is not also 'room'."""
    taken = [False] * len(text)
    hits: list[tuple[int, str]] = []
    for pat, canon in patterns:
        for m in pat.finditer(text):
            if any(taken[m.start() : m.end()]):
                continue
            for k in range(m.start(), m.end()):
                taken[k] = True
            hits.append((m.start(), canon))
    hits.sort()
    out: list[str] = []
    for _, canon in hits:
        if canon not in out:
            out.append(canon)
    return out


def _turn_of(clause: str) -> Turn | None:
    if re.search(r"\b(turn|spin|go|head)\s+(all the way\s+)?around\b|\bturn back\b|\bu-?turn\b|\b180\b", clause):
        return Turn.AROUND
    slight = re.search(r"\b(slight|slightly|bear|veer|a little)\b", clause)
    if re.search(r"\bleft\b", clause) and not re.search(
        r"\bon (the|your) left\b|\bleft of\b|\bto the left of\b", clause
    ):
        return Turn.SLIGHT_LEFT if slight else Turn.LEFT
    if re.search(r"\bright\b", clause) and not re.search(
        r"\bon (the|your) right\b|\bright of\b|\bto the right of\b|\bright (in front|next|by|beside)\b", clause
    ):
        return Turn.SLIGHT_RIGHT if slight else Turn.RIGHT
    if re.search(r"\b(straight|forward|ahead)\b", clause):
        return Turn.STRAIGHT
    return None


def _distance_of(clause: str) -> float | None:
    m = _DISTANCE.search(clause)
    if not m:
        return None
    raw, unit = m.group(1), m.group(2)
    value = float(raw) if raw[0].isdigit() else float(_NUMBERS[raw])
    if unit.startswith(("m", "meter", "metre")):
        return value
    if unit.startswith(("feet", "foot", "ft")):
        return value * 0.3048
    if unit.startswith("yard"):
        return value * 0.9144
    return value * _STEP_LENGTH_M


@dataclass
class SubGoal:
    """One clause of the instruction."""

    text: str
    turn: Turn | None = None
    distance_m: float | None = None
    rooms: list[str] = field(default_factory=list)
    landmarks: list[str] = field(default_factory=list)
    stop: bool = False
    leave: bool = False  # "exit the kitchen": done once the agent is out of ``rooms``

    @property
    def targets(self) -> list[str]:
        """What to look for: a room being left is not sought."""
        return self.landmarks + ([] if self.leave else self.rooms)

    @property
    def is_empty(self) -> bool:
        return self.turn is None and self.distance_m is None and not self.rooms and not self.landmarks and not self.stop


@dataclass
class ParsedInstruction:
    text: str
    subgoals: list[SubGoal]

    @property
    def final_landmarks(self) -> list[str]:
        """Where to stop: the landmarks of the stop clause, else those of the last clause naming one."""
        for sg in self.subgoals:
            if sg.stop and sg.landmarks:
                return sg.landmarks
        for sg in reversed(self.subgoals):
            if sg.landmarks:
                return sg.landmarks[-1:]
        return []

    @property
    def final_rooms(self) -> list[str]:
        for sg in reversed(self.subgoals):
            if sg.rooms:
                return sg.rooms[-1:]
        return []


def parse_instruction(text: str) -> ParsedInstruction:
    """Split an instruction into ordered sub-goals (clauses with a turn, a distance, rooms, landmarks)."""
    norm = text.lower().replace("’", "'")
    clauses = [c.strip() for c in _CLAUSE_SPLIT.split(norm)]
    subgoals: list[SubGoal] = []
    for clause in clauses:
        if not clause:
            continue
        sg = SubGoal(
            text=clause,
            turn=_turn_of(clause),
            distance_m=_distance_of(clause),
            rooms=_find_ordered(clause, _ROOM_PATTERNS),
            landmarks=_find_ordered(clause, _LANDMARK_PATTERNS),
            stop=bool(_STOP.search(clause)),
        )
        sg.leave = bool(sg.rooms) and bool(_LEAVE.search(clause)) and not sg.stop
        if sg.is_empty:
            continue
        # "stop" alone ("... and stop") belongs to the previous clause's target.
        if sg.stop and not sg.targets and sg.turn is None and subgoals:
            subgoals[-1].stop = True
            continue
        subgoals.append(sg)
    return ParsedInstruction(text=text, subgoals=subgoals)


def label_matches(label_name: str, target: str) -> bool:
    """Whether a scene label ('kitchen floor', 'sofa', 'bed frame') shows a canonical target."""
    name = label_name.lower().replace("_", " ").replace("-", " ")
    phrases = ROOMS.get(target) or LANDMARKS.get(target) or (target,)
    for p in (target, *phrases):
        if re.search(rf"\b{re.escape(p)}\b", name):
            return True
    return False
