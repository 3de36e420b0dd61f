"""Every key expression of the system, in one place (the topology, like dora's dataflow.yml).

Each :class:`Key` names its template, who owns it (serves or publishes on it), who consumes it (queries
or subscribes), how it is used (``queryable`` / ``publication`` / ``liveliness``) and the schemas it
carries. Services and tests
build concrete keys with :meth:`Key.format`, which validates the ``{robot}``, ``{map}``, ... parts so
that a caller can never inject ``*``, ``**``, ``/`` or ``$`` into a key expression.

The README's dataflow diagram and key table (``python -m shared.keys``) and the access-control rules
in ``deploy/`` are derived from :data:`CATALOGUE`; a test keeps the README in step.
"""

from __future__ import annotations

import re
import string
from dataclasses import dataclass
from enum import StrEnum

ROOT = "ant"
# One key segment: what zenoh would otherwise read as a wildcard, separator or verbatim chunk is refused.
# Written once: the schemas' ``SegmentId`` and the gateway's path parameters use this same pattern.
SEGMENT_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_SEGMENT = re.compile(SEGMENT_PATTERN)


class KeyExprError(ValueError):
    """A key part is not a valid single segment."""


class KeyMismatch(KeyExprError):
    """A payload names another id than the key it came on (a forged or confused request): refused,
    because the key is what the ACL and the caller's route vouch for, the payload is not."""


def validate_segment(value: str, what: str = "key part") -> str:
    if not isinstance(value, str) or not _SEGMENT.match(value):
        raise KeyExprError(
            f"invalid {what} {value!r}: 1-64 characters of letters, digits, '_', '-', '.', "
            "starting with a letter or digit"
        )
    return value


def routed(key: str, instance: str) -> str:
    """The instance-only route of a shared queryable (``<key>/@<instance>``).

    ``@`` makes the last chunk *verbatim* in zenoh: no wildcard matches it, so ``ant/**`` never
    reaches these routes by accident, while a client that wants one replica addresses it exactly.
    """
    return f"{key}/@{validate_segment(instance, 'instance')}"


def robot_routes(key: "Key", robots: "tuple[str, ...] | list[str]" = (), **parts: str) -> list[str]:
    """What a service serving many robots declares for ``key``: the wildcard expression (every robot,
    ``ant/*/...``) when ``robots`` is empty, else each given robot's concrete key - so that replicas can
    split the robots between them instead of zenoh picking one replica for every robot."""
    if not robots:
        return [key.pattern(**parts)]
    return [key.format(robot=r, **parts) for r in dict.fromkeys(robots)]


def ids_of(key: "Key", asked: str) -> dict[str, str]:
    """The named segments (``{"map": ..., "build": ...}``) of the concrete key a request or sample came
    on, an instance route's ``/@x`` ignored. Identity comes from the key, never from a payload.
    Raises :class:`KeyExprError` for a key that is not one of ``key``'s (e.g. a wildcard asked)."""
    segs = asked.split("/")
    if segs and segs[-1].startswith("@"):
        segs = segs[:-1]
    found = key.parse("/".join(segs))
    if found is None:
        raise KeyExprError(f"{asked!r} is not a concrete key of {key.template}")
    return found


def robot_of(key: "Key", asked: str) -> str:
    """The robot id in the concrete key a request came on: a request on robotX's key can only act on
    robotX. Raises :class:`KeyExprError` for a key that is not one of ``key``'s."""
    found = ids_of(key, asked)
    if "robot" not in found:
        raise KeyExprError(f"{key.template} has no robot segment")
    return found["robot"]


def agree(key: "Key", asked: str, payload: object, **fields: str) -> dict[str, str]:
    """The key's ids, after checking that each payload attribute named in ``fields`` (``map="map_id"``:
    key part -> payload attribute) equals the key's segment. Raises :class:`KeyMismatch` (a bad
    request) when one differs: a request on map A's key can never act on map B."""
    found = ids_of(key, asked)
    for part, attr in fields.items():
        if part not in found:
            raise KeyExprError(f"{key.template} has no {{{part}}} segment")
        claimed = getattr(payload, attr)
        if claimed != found[part]:
            raise KeyMismatch(f"{attr} {claimed!r} disagrees with the key's {part} {found[part]!r} ({asked})")
    return found


class Usage(StrEnum):
    QUERYABLE = "queryable"
    PUBLICATION = "publication"
    LIVELINESS = "liveliness"


@dataclass(frozen=True)
class Key:
    template: str
    owner: str
    usage: Usage
    request: str = ""
    reply: str = ""
    doc: str = ""
    consumers: tuple[str, ...] = ()  # who queries or subscribes: the other end of the dataflow

    @property
    def parts(self) -> list[str]:
        return [f for _, f, _, _ in string.Formatter().parse(self.template) if f]

    def format(self, **parts: str) -> str:
        """The concrete key; every part must be given and valid."""
        missing = set(self.parts) - parts.keys()
        if missing:
            raise KeyExprError(f"{self.template}: missing {sorted(missing)}")
        return self.template.format(**{k: validate_segment(v, k) for k, v in parts.items()})

    def pattern(self, **parts: str) -> str:
        """A wildcard expression: given parts fixed, the others ``*``."""
        values = {p: validate_segment(parts[p], p) if p in parts else "*" for p in self.parts}
        return self.template.format(**values)

    def parse(self, key: str) -> dict[str, str] | None:
        """The parts of a concrete key of this template (None: not one of its keys). What a
        subscriber trusts about a sample's identity: the key it came on, not the payload's claims."""
        names, segs = self.template.split("/"), key.split("/")
        if len(names) != len(segs):
            return None
        out: dict[str, str] = {}
        for name, seg in zip(names, segs):
            if name.startswith("{") and name.endswith("}"):
                try:
                    out[name[1:-1]] = validate_segment(seg)
                except KeyExprError:
                    return None
            elif name != seg:
                return None
        return out


_R = ROOT + "/{robot}"

# --- liveliness and per-instance plumbing (every service) -----------------------------------------
ALIVE = Key(f"{ROOT}/alive/{{service}}/{{instance}}", "*", Usage.LIVELINESS,
            doc="liveliness token of one running service instance",
            consumers=("gateway", "planner", "mapper"))
INFO = Key(f"{ROOT}/svc/{{service}}/{{instance}}/info", "*", Usage.QUERYABLE, "Ping", "ServiceInfo",
           "name, version, instance id and backends of one instance",
            consumers=("gateway",))
METRICS = Key(f"{ROOT}/svc/{{service}}/{{instance}}/metrics", "*", Usage.QUERYABLE, "Ping", "ServiceMetrics",
              "request/error counters, latencies and queue depth of one instance",
            consumers=("gateway",))

# --- robot-io ---------------------------------------------------------------------------------------
IO_OBSERVE = Key(f"{_R}/io/observe", "robot_io", Usage.QUERYABLE, "ObserveRequest", "Panorama",
                 "a 12-view RGB-D(-semantic) panorama at the current pose",
            consumers=("planner", "mapper"))
IO_MOVE = Key(f"{_R}/io/move_to", "robot_io", Usage.QUERYABLE, "MoveRequest", "MoveResult",
              "walk to a waypoint (dx, dy) with collision handling",
            consumers=("planner", "mapper"))
IO_TURN = Key(f"{_R}/io/turn", "robot_io", Usage.QUERYABLE, "TurnRequest", "PoseReply", "turn in place",
            consumers=("mapper",))
IO_LOOK = Key(f"{_R}/io/look_around", "robot_io", Usage.QUERYABLE, "Ping", "PoseReply",
              "+-60 deg yaw, +-45 deg pitch sweep",
            consumers=("mapper",))
IO_RESET = Key(f"{_R}/io/reset", "robot_io", Usage.QUERYABLE, "ResetRequest", "PoseReply", "teleport / reset",
            consumers=("planner", "mapper"))
IO_GEODESIC = Key(f"{_R}/io/geodesic", "robot_io", Usage.QUERYABLE, "GeodesicRequest", "GeodesicReply",
                  "geodesic distance and shortest path (simulator oracle for metrics)",
            consumers=("planner", "mapper"))
IO_VIEWS = Key(f"{_R}/io/views", "robot_io", Usage.QUERYABLE, "SceneViewsRequest", "RenderResult",
               "views ray-cast from the true scene at given poses (simulator only: the evaluation's true-scene "
               "anticipation control)",
            consumers=("planner",))
IO_RECORD = Key(f"{_R}/io/record", "robot_io", Usage.QUERYABLE, "RecordRequest", "RecordReply",
                "start/stop recording a tour (frames published on IO_FRAMES)",
            consumers=("mapper",))
IO_SCENE = Key(f"{_R}/io/scene", "robot_io", Usage.QUERYABLE, "Ping", "SceneSummary",
               "what the robot knows of its scene (rooms, labels, bounds)",
            consumers=("gateway", "mapper"))
IO_LOAD_SCENE = Key(f"{_R}/io/scene/load", "robot_io", Usage.QUERYABLE, "LoadSceneRequest", "SceneSummary",
                    "load another scene (simulator backends; evaluation over many houses)",
            consumers=("gateway",))
IO_POSE = Key(f"{_R}/io/pose", "robot_io", Usage.PUBLICATION, reply="Pose", doc="pose after every motion",
            consumers=())
IO_FRAMES = Key(f"{_R}/io/frames/{{recording}}", "robot_io", Usage.PUBLICATION, reply="Frame",
                doc="recorded tour frames at a fixed rate",
            consumers=("reconstructor",))

# --- mapper -----------------------------------------------------------------------------------------
MAPPER_PREDICT = Key(f"{_R}/mapper/predict", "mapper", Usage.QUERYABLE, "Panorama", "CandidateSet",
                     "waypoint candidates for a panorama",
            consumers=("planner",))
MAPPER_GRAPH = Key(f"{_R}/mapper/graph", "mapper", Usage.PUBLICATION, reply="NavGraph",
                   doc="the explored navigation graph",
            consumers=())
MAPPER_TOURS = Key(f"{_R}/mapper/tours/{{region}}", "mapper", Usage.PUBLICATION, reply="Tour",
                   doc="planned recording tour per region",
            consumers=())

MAPPER_EXPLORE = Key(f"{_R}/mapper/explorations/submit", "mapper", Usage.QUERYABLE, "ExplorationRequest",
                     "JobAccepted", "start pre-exploration + tour recording + reconstruction",
            consumers=("gateway",))
EXPLORATION_CANCEL = Key(f"{_R}/mapper/explorations/cancel", "mapper", Usage.QUERYABLE, "ExplorationCancelRequest",
                         "JobAccepted", "cancel a running exploration (discovery, tours, or the map build it waits on)",
            consumers=("gateway",))
EXPLORATION_EVENTS = Key(f"{_R}/explorations/{{exploration}}/events", "mapper", Usage.PUBLICATION,
                         reply="JobEvent", doc="exploration progress events (mission_id = exploration id)",
            consumers=("gateway",))

# --- maps (reconstructor owns the map store) --------------------------------------------------------
MAP_LIST = Key(f"{ROOT}/maps/list", "reconstructor", Usage.QUERYABLE, "Ping", "MapListReply", "list maps",
            consumers=("gateway",))
MAP_INFO = Key(f"{ROOT}/maps/{{map}}/info", "reconstructor", Usage.QUERYABLE, "MapRequest", "MapInfo",
               "metadata of one map",
            consumers=("gateway", "planner", "renderer"))
MAP_CHUNK = Key(f"{ROOT}/maps/{{map}}/chunk", "reconstructor", Usage.QUERYABLE, "MapChunkRequest", "MapChunk",
                "the map's points, in chunks",
            consumers=("gateway", "renderer"))
MAP_SCENE_GRAPH = Key(f"{ROOT}/maps/{{map}}/scene-graph", "reconstructor", Usage.QUERYABLE, "SceneGraphRequest",
                      "SceneGraph", "the scene graph of a map version (rooms, objects, stairs, navigation graph)",
                      consumers=("gateway", "planner"))
MAP_BUILD = Key(f"{ROOT}/maps/{{map}}/build", "reconstructor", Usage.QUERYABLE, "BuildMapRequest", "JobAccepted",
                "start a job that reconstructs recorded tours into a stored map",
            consumers=("mapper",))
MAP_BUILD_CANCEL = Key(f"{ROOT}/maps/{{map}}/builds/cancel", "reconstructor", Usage.QUERYABLE, "BuildCancelRequest",
                       "JobAccepted", "cancel a map build of this map (nothing of it is stored)",
                       consumers=("mapper",))
MAP_BUILD_EVENTS = Key(f"{ROOT}/maps/{{map}}/builds/{{build}}/events", "reconstructor", Usage.PUBLICATION,
                       reply="JobEvent", doc="a map build's progress and its stored map (or why it failed)",
                       consumers=("mapper",))
MAP_IMPORT = Key(f"{ROOT}/maps/{{map}}/import", "reconstructor", Usage.QUERYABLE, "MapImportRequest", "MapInfo",
                 "store an uploaded PLY/PCD cloud as a map",
            consumers=("gateway",))
MAP_UPDATED = Key(f"{ROOT}/maps/{{map}}/updated", "reconstructor", Usage.PUBLICATION, reply="MapInfo",
                  doc="a new version of a map was stored",
            consumers=("renderer",))

# --- renderer -----------------------------------------------------------------------------------------
RENDER_VIEWS = Key(f"{ROOT}/render/views", "renderer", Usage.QUERYABLE, "RenderRequest", "RenderResult",
                   "anticipated views of one step (batch)",
            consumers=("planner",))
RENDER_MAP = Key(f"{ROOT}/render/spatial_map", "renderer", Usage.QUERYABLE, "SpatialMapRequest",
                 "SpatialMapResult", "top-down spatial map image",
            consumers=("planner",))

# --- planner / missions ---------------------------------------------------------------------------------
MISSION_SUBMIT = Key(f"{_R}/planner/missions/submit", "planner", Usage.QUERYABLE, "MissionRequest",
                     "JobAccepted", "start a navigation mission",
            consumers=("gateway",))
MISSION_CANCEL = Key(f"{_R}/planner/missions/cancel", "planner", Usage.QUERYABLE, "CancelRequest",
                     "JobAccepted", "cancel a running mission",
            consumers=("gateway",))
MISSION_EVENTS = Key(f"{_R}/missions/{{mission}}/events", "planner", Usage.PUBLICATION, reply="JobEvent",
                     doc="mission events (started, step, finished, error)",
            consumers=("gateway",))

CATALOGUE: tuple[Key, ...] = tuple(v for v in globals().values() if isinstance(v, Key))


def markdown_table() -> str:
    """The catalogue as the README's Markdown table."""
    rows = ["| key expression | owner | consumers | usage | request | reply / sample |", "|---|---|---|---|---|---|"]
    rows += [f"| `{k.template}` | {k.owner} | {', '.join(k.consumers) or '-'} | {k.usage} | {k.request or '-'} "
             f"| {k.reply or '-'} |" for k in CATALOGUE]
    return "\n".join(rows)


def dataflow_mermaid() -> str:
    """Who talks to whom, as a Mermaid flowchart, labelled with the keys (their fixed segments).

    A solid arrow is a query, from the consumer that asks to the owner that answers; a dotted arrow is
    a publication (or liveliness), from the owner to its subscribers. Per-instance plumbing (owner ``*``)
    is left out: every service has it."""
    edges: dict[tuple[str, str, bool], set[str]] = {}
    for k in CATALOGUE:
        if k.owner == "*":
            continue
        label = "/".join(p for p in k.template.split("/")[1:] if not p.startswith("{"))
        query = k.usage == Usage.QUERYABLE
        for c in k.consumers:
            edges.setdefault((c, k.owner, True) if query else (k.owner, c, False), set()).add(label)
    lines = ["flowchart LR"]
    for (src, dst, query), labels in sorted(edges.items()):
        lines.append(f"    {src} {'-->' if query else '-.->'}|{', '.join(sorted(labels))}| {dst}")
    return "\n".join(lines)


_BEGIN = "<!-- BEGIN {name}: generated by `python -m shared.keys --write README.md`; a test checks it -->"
_END = "<!-- END {name} -->"


def readme_blocks() -> dict[str, str]:
    """The README's generated blocks: the dataflow diagram and the key table."""
    return {"dataflow": "```mermaid\n" + dataflow_mermaid() + "\n```", "keys": markdown_table()}


def render_readme(text: str) -> str:
    """``text`` with every generated block replaced by its current content (markers kept)."""
    for name, body in readme_blocks().items():
        begin, end = _BEGIN.format(name=name), _END.format(name=name)
        i, j = text.find(begin), text.find(end)
        if i < 0 or j < i:
            raise ValueError(f"README has no {name!r} block ({begin} ... {end})")
        text = text[: i + len(begin)] + "\n" + body + "\n" + text[j:]
    return text


if __name__ == "__main__":
    import sys
    from pathlib import Path

    if sys.argv[1:2] == ["--write"] and len(sys.argv) == 3:
        path = Path(sys.argv[2])
        path.write_text(render_readme(path.read_text()))
    else:
        for body in readme_blocks().values():
            print(body + "\n")
