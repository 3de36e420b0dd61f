"""Rerun (``.rrd``) recordings of missions and explorations, for inspection in the Rerun viewer.

A recording is written from a job's event stream (the same :class:`~shared.schemas.JobEvent`\\ s
the gateway stores and the dashboard shows) plus, when given, the map's cloud. Entities:

| entity | what | when |
|---|---|---|
| ``world/map`` | the map cloud (Points3D, subsampled to ``max_points``) | static |
| ``world/trajectory`` | the path walked so far (LineStrips3D) | per step |
| ``world/agent`` | the agent's position and heading (Points3D + Arrows3D at ``world/agent/heading``) | per step |
| ``world/candidates`` | every candidate's target point, labelled ``#i kind`` | per step |
| ``world/chosen`` | the chosen candidate's target | per step |
| ``world/goal`` | the goal and the reference path, when the job has them | static |
| ``world/scene_graph/rooms`` | the map's scene graph: room centroids labelled with their names ("bedroom 2") | static |
| ``world/scene_graph/footprints`` | each room's floor outline (LineStrips3D, labelled) | static |
| ``world/scene_graph/objects`` | objects at their positions in their dominant colour, labelled "red bed" | static |
| ``world/scene_graph/openings`` | doors and openings, labelled with the two rooms they join | static |
| ``world/scene_graph/navigation`` | the exploration's navigation graph: one line strip per edge, nodes as points | static |
| ``world/scene_graph/stairs`` | stairways, bottom to top | static |
| ``views/panorama``, ``views/spatial_map`` | the observed panorama and the spatial map (JPEG) | per step (an exploration: per progress event with a map) |
| ``views/candidates/<i>/observed`` / ``anticipated`` | each candidate's observed and anticipated view | per step |
| ``decisions`` | the decision and its reasoning (TextLog) | per step |
| ``timings/<name>`` | per-step timings in seconds (Scalars) | per step |
| ``events`` | started, progress, finished and error messages (TextLog) | per event |
| ``progress`` | an exploration's progress 0-1 (Scalars) | per progress event |

Timelines: ``step`` (the mission step, or the event's seq for an exploration) and ``time`` (the
event's timestamp). ``rerun-sdk`` is imported lazily: importing it costs ~0.6 s, and only writers need it.

``python -m shared.recording open FILE.rrd`` opens a recording in the viewer shipped with the wheel;
``python -m shared.recording fetch --gateway URL --mission ID`` downloads one first.
"""

from __future__ import annotations

import argparse
import logging
import math
import subprocess
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.scene_names import room_names
from shared.schemas import JobEvent, JobEventKind, JobState, SceneGraph

log = logging.getLogger(__name__)

APPLICATION_ID = "spatialant"
_CAND_COLOURS = {"waypoint": (240, 150, 20), "backtrack": (160, 60, 200), "stop": (220, 40, 40)}
_CHOSEN = (40, 200, 80)
_PATH = (30, 120, 220)
_GOAL = (220, 40, 40)
_REFERENCE = (90, 90, 90)
_ROOM = (30, 120, 50)
_OPENING = (230, 126, 34)
_NAV = (120, 120, 200)
_STAIRS = (160, 60, 200)


@dataclass(frozen=True)
class RecordedEvent:
    """One event of a job as the gateway stores it: the payload as JSON values (``JobEvent.data_json``).

    Recordings read this form, not the typed message, so that events stored by an older version of a
    service (whose payload the current schema might refuse) still make a recording.
    """

    seq: int
    kind: JobEventKind
    state: JobState
    step: int
    timestamp_s: float
    data: dict[str, Any]
    images: dict[str, bytes] = field(default_factory=dict)

    @classmethod
    def from_message(cls, ev: JobEvent) -> RecordedEvent:
        return cls(ev.seq, ev.kind, ev.state, ev.step, ev.timestamp_s, ev.data_json(), dict(ev.images))


@dataclass
class RecordingInput:
    """What a recording is made of: the job's events (in seq order) and optionally the map cloud."""

    job_id: str
    job_kind: str  # "mission" or "exploration"
    events: list[RecordedEvent]
    cloud_xyz_m: np.ndarray | None = None
    cloud_rgb: np.ndarray | None = None
    map_id: str = ""
    info: dict[str, Any] = field(default_factory=dict)  # free-form, logged as the recording's description
    options: dict[str, Any] = field(default_factory=dict)  # the job's options as requested (goal, reference)
    scene_graph: SceneGraph | None = None  # the map's scene graph (issue 32), drawn under world/scene_graph


def _xyz(p: Any) -> np.ndarray | None:
    try:
        a = np.asarray(p, np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    return a if np.all(np.isfinite(a)) else None


def write_recording(inp: RecordingInput, path: Path | str, *, max_points: int = 500_000, seed: int = 0) -> Path:
    """Write ``inp`` as an ``.rrd`` at ``path`` (atomically: a partial file is never left behind)."""
    import rerun as rr

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".part")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=inp.job_id)
    try:
        rec.save(tmp)
        _log_static(rr, rec, inp, max_points, seed)
        trajectory: list[np.ndarray] = []
        for ev in sorted(inp.events, key=lambda e: e.seq):
            _log_event(rr, rec, inp, ev, trajectory)
        rec.flush(timeout_sec=60.0)
    finally:
        rec.disconnect()
    tmp.replace(path)
    return path


def _log_static(rr, rec, inp: RecordingInput, max_points: int, seed: int) -> None:
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    desc = [f"SpatialAnt {inp.job_kind} {inp.job_id}"] + ([f"map {inp.map_id}"] if inp.map_id else [])
    desc += [f"{k}: {v}" for k, v in inp.info.items()]
    rec.log("description", rr.TextDocument("\n\n".join(desc), media_type=rr.MediaType.MARKDOWN), static=True)
    if inp.cloud_xyz_m is not None and len(inp.cloud_xyz_m):
        xyz = np.asarray(inp.cloud_xyz_m, np.float32)
        rgb = np.asarray(inp.cloud_rgb, np.uint8) if inp.cloud_rgb is not None else None
        if len(xyz) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
            xyz, rgb = xyz[keep], (rgb[keep] if rgb is not None else None)
        rec.log("world/map", rr.Points3D(xyz, colors=rgb, radii=0.015), static=True)
    # The goal and reference path: in the started event's options (the planner's), else the request's.
    started = next((ev.data.get("options") for ev in inp.events if ev.kind == JobEventKind.STARTED), None)
    opts = started or inp.options
    goal = _xyz(opts.get("goal_m"))
    if goal is not None:
        rec.log("world/goal", rr.Points3D([goal], colors=[_GOAL], radii=0.12, labels=["goal"]), static=True)
    ref = [p for p in (_xyz(q) for q in opts.get("reference_path_m") or []) if p is not None]
    if len(ref) >= 2:
        rec.log("world/reference", rr.LineStrips3D([np.asarray(ref)], colors=[_REFERENCE], radii=0.03), static=True)
    if inp.scene_graph is not None:
        _log_scene_graph(rr, rec, inp.scene_graph)


def _log_scene_graph(rr, rec, graph: SceneGraph) -> None:
    """The map's scene graph, static, under ``world/scene_graph`` (see the module's table). Names sit a
    little above the floor so that the cloud's floor points do not hide them."""
    names = room_names(graph)
    root = "world/scene_graph"
    if graph.rooms:
        floor_z = {r.room_id: r.floor_z_m for r in graph.rooms}
        rec.log(f"{root}/rooms", rr.Points3D([(r.centroid_m[0], r.centroid_m[1], r.floor_z_m + 0.3) for r in graph.rooms],
                                             colors=[_ROOM], radii=0.12, labels=[names[r.room_id] for r in graph.rooms],
                                             show_labels=True), static=True)
        loops = [(r, [(x, y, floor_z[r.room_id] + 0.02) for x, y in [*r.footprint_m, r.footprint_m[0]]])
                 for r in graph.rooms if len(r.footprint_m) >= 3]
        if loops:
            rec.log(f"{root}/footprints", rr.LineStrips3D([p for _, p in loops], colors=[_ROOM], radii=0.02,
                                                          labels=[names[r.room_id] for r, _ in loops],
                                                          show_labels=False), static=True)
    if graph.objects:
        rec.log(f"{root}/objects", rr.Points3D([o.position_m for o in graph.objects],
                                               colors=[o.colour_rgb for o in graph.objects], radii=0.08,
                                               labels=[f"{o.colour} {o.label}".strip() for o in graph.objects],
                                               show_labels=False), static=True)
    if graph.openings:
        rec.log(f"{root}/openings", rr.Points3D([o.position_m for o in graph.openings], colors=[_OPENING], radii=0.1,
                                                labels=[f"{names[o.a]} - {names[o.b]}" for o in graph.openings],
                                                show_labels=False), static=True)
    nav = graph.navigation
    if nav.nodes:
        at = {n.node_id: n.position_m for n in nav.nodes}
        strips = [[at[e.a], at[e.b]] for e in nav.edges if e.a in at and e.b in at]
        rec.log(f"{root}/navigation/nodes", rr.Points3D([n.position_m for n in nav.nodes], colors=[_NAV], radii=0.05),
                static=True)
        if strips:
            rec.log(f"{root}/navigation", rr.LineStrips3D(strips, colors=[_NAV], radii=0.015), static=True)
    if graph.stairs:
        rec.log(f"{root}/stairs", rr.LineStrips3D([[s.bottom_m, s.top_m] for s in graph.stairs], colors=[_STAIRS],
                                                  radii=0.05, labels=[f"stairs {s.from_floor}-{s.to_floor}"
                                                                      for s in graph.stairs]), static=True)


def _log_event(rr, rec, inp: RecordingInput, ev: RecordedEvent, trajectory: list[np.ndarray]) -> None:
    step = ev.step if inp.job_kind == "mission" else ev.seq
    rec.set_time("step", sequence=int(step))
    rec.set_time("time", timestamp=float(ev.timestamp_s))
    d = ev.data or {}
    for name, data in (ev.images or {}).items():  # a step's views, an exploration's map so far
        rec.log(_image_entity(name), rr.EncodedImage(contents=data, media_type="image/jpeg"))
    if ev.kind == JobEventKind.STEP:
        _log_step(rr, rec, ev, d, trajectory)
        return
    level = "ERROR" if ev.kind == JobEventKind.ERROR else "INFO"
    text = d.get("message") or d.get("error") or d.get("reason") or ""
    rec.log("events", rr.TextLog(f"{ev.kind.value} ({ev.state.value}) {text}".strip(), level=level))
    if ev.kind == JobEventKind.PROGRESS and isinstance(d.get("progress"), (int, float)):
        rec.log("progress", rr.Scalars(float(d["progress"])))
    if ev.kind == JobEventKind.STARTED:
        p = _xyz((d.get("pose") or {}).get("position_m"))
        if p is not None:
            trajectory.append(p)
    if ev.kind == JobEventKind.FINISHED:
        # The final pose after the last move is only in the finished event (the whole path, or the pose).
        pts = [q for q in (_xyz(p) for p in d.get("trajectory_m") or []) if q is not None]
        end = _xyz((d.get("pose") or {}).get("position_m"))
        if not pts and end is not None:
            pts = [*trajectory, end] if not trajectory or np.linalg.norm(trajectory[-1] - end) > 1e-6 else trajectory
        if len(pts) >= 2:
            rec.log("world/trajectory", rr.LineStrips3D([np.asarray(pts)], colors=[_PATH], radii=0.04))
        if pts:
            rec.log("world/agent", rr.Points3D([pts[-1]], colors=[_PATH], radii=0.15))
        metrics = d.get("metrics")
        if isinstance(metrics, dict):
            for k, v in metrics.items():
                if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                    rec.log(f"metrics/{k}", rr.Scalars(float(v)))


def _log_step(rr, rec, ev: RecordedEvent, d: dict, trajectory: list[np.ndarray]) -> None:
    pose = d.get("pose") or {}
    here = _xyz(pose.get("position_m"))
    heading = float(pose.get("heading_rad", 0.0) or 0.0)
    if here is not None:
        if not trajectory or np.linalg.norm(trajectory[-1] - here) > 1e-6:
            trajectory.append(here)
        rec.log("world/agent", rr.Points3D([here], colors=[_PATH], radii=0.15))
        rec.log("world/agent/heading", rr.Arrows3D(origins=[here], vectors=[[0.6 * math.cos(heading),
                                                                           0.6 * math.sin(heading), 0.0]]))
    if len(trajectory) >= 2:
        rec.log("world/trajectory", rr.LineStrips3D([np.asarray(trajectory)], colors=[_PATH], radii=0.04))
    decision = d.get("decision") or {}
    chosen = decision.get("candidate_index")
    cands = d.get("candidates") or []
    if here is not None and cands:
        pts, colours, labels = [], [], []
        chosen_pt = None
        for c in cands:
            kind = str(c.get("kind", "waypoint"))
            p = here + np.array([float(c.get("dx_m", 0.0)), float(c.get("dy_m", 0.0)), 0.0])
            pts.append(p)
            colours.append(_CAND_COLOURS.get(kind, (200, 200, 200)))
            labels.append(f"#{c.get('index')} {kind}")
            if c.get("index") == chosen:
                chosen_pt = p
        rec.log("world/candidates", rr.Points3D(pts, colors=colours, radii=0.1, labels=labels))
        if chosen_pt is not None:
            rec.log("world/chosen", rr.Points3D([chosen_pt], colors=[_CHOSEN], radii=0.16))
    kind = decision.get("kind", "?")
    reasoning = d.get("reasoning") or decision.get("reasoning") or ""
    rec.log("decisions", rr.TextLog(f"step {ev.step}: {kind} #{chosen} - {reasoning}".strip(" -"), level="INFO"))
    for name, v in (d.get("timings_s") or {}).items():
        if isinstance(v, (int, float)) and math.isfinite(v):
            rec.log(f"timings/{name}", rr.Scalars(float(v)))


def _image_entity(name: str) -> str:
    """``cand_3_observed`` -> ``views/candidates/3/observed``; ``map`` -> ``views/spatial_map``."""
    parts = name.split("_")
    if len(parts) == 3 and parts[0] == "cand":
        return f"views/candidates/{parts[1]}/{parts[2]}"
    return {"map": "views/spatial_map"}.get(name, f"views/{name}")


def entity_rows(path: Path | str) -> dict[str, int]:
    """Rows logged per entity in an ``.rrd`` (rerun's own reader), e.g. for a CLI summary."""
    import rerun as rr

    counts: dict[str, int] = {}
    for chunk in rr.chunk.RrdReader(str(path)).stream():
        name = chunk.entity_path.lstrip("/")
        counts[name] = counts.get(name, 0) + chunk.num_rows
    return counts


# --- command line ------------------------------------------------------------------------------------


def open_in_viewer(path: Path | str, *, wait: bool = False) -> subprocess.Popen:
    """Start the Rerun viewer (shipped in the rerun-sdk wheel, works offline) on ``path``."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no recording at {p}")
    proc = subprocess.Popen([sys.executable, "-m", "rerun", str(p)])
    if wait:
        proc.wait()
    return proc


def _fetch(gateway: str, kind: str, job_id: str, out: Path, token: str | None) -> Path:
    import httpx

    headers = {"Authorization": f"Bearer {token}"} if token else {}
    url = f"{gateway.rstrip('/')}/{kind}s/{job_id}/recording.rrd"
    with httpx.stream("GET", url, headers=headers, timeout=300.0) as r:
        if r.status_code != 200:
            r.read()
            raise SystemExit(f"GET {url}: {r.status_code} {r.text[:300]}")
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "wb") as f:
            for block in r.iter_bytes():
                f.write(block)
    return out


def main(argv: Iterable[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m shared.recording", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    o = sub.add_parser("open", help="open an .rrd in the Rerun viewer")
    o.add_argument("path", type=Path)
    s = sub.add_parser("summary", help="print the rows per entity of an .rrd")
    s.add_argument("path", type=Path)
    f = sub.add_parser("fetch", help="download a job's recording from the gateway (and open it)")
    f.add_argument("--gateway", default="http://127.0.0.1:8000")
    who = f.add_mutually_exclusive_group(required=True)
    who.add_argument("--mission")
    who.add_argument("--exploration")
    f.add_argument("--out", type=Path, default=None, help="default: runs/recordings/<id>.rrd")
    f.add_argument("--token", default=None)
    f.add_argument("--open", action="store_true", help="open it in the viewer afterwards")
    a = p.parse_args(list(argv) if argv is not None else None)
    if a.command == "open":
        open_in_viewer(a.path, wait=True)
    elif a.command == "summary":
        for entity, rows in sorted(entity_rows(a.path).items()):
            print(f"{rows:6d}  {entity}")
    else:
        kind, job_id = ("mission", a.mission) if a.mission else ("exploration", a.exploration)
        out = _fetch(a.gateway, kind, job_id, a.out or Path("runs/recordings") / f"{job_id}.rrd", a.token)
        print(out)
        if a.open:
            open_in_viewer(out, wait=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
