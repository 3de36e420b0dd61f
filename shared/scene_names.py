"""Display names of a scene graph's rooms, one rule for every surface (prompt text, spatial map, Rerun
recording; the dashboard's app.js repeats it in JavaScript): a room type seen once is "kitchen", several
are numbered in the graph's room order ("bedroom 1", "bedroom 2"), an unnamed room is "room N"."""

from __future__ import annotations

from collections import Counter

from shared.schemas import SceneGraph


def room_names(graph: SceneGraph) -> dict[str, str]:
    """room_id -> display name (see the module docstring)."""
    counts = Counter(r.room_type for r in graph.rooms if r.room_type)
    seen: Counter[str] = Counter()
    out: dict[str, str] = {}
    for k, r in enumerate(graph.rooms):
        if not r.room_type:
            out[r.room_id] = f"room {k + 1}"
            continue
        seen[r.room_type] += 1
        out[r.room_id] = r.room_type if counts[r.room_type] == 1 else f"{r.room_type} {seen[r.room_type]}"
    return out
