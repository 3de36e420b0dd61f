"""The numbers of a schema, as data: every numeric leaf of a model (recursively), with its bounds,
and well-formed payloads that put a non-finite, huge or out-of-range value into one leaf each.

Used by the schema test (every number of every request schema is bounded) and by the bus fuzz of the
reliability suite (every such value on every queryable is refused, and the system still works).
"""

from __future__ import annotations

import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import annotated_types as at
import msgpack
from pydantic import BaseModel

from shared import keys, schemas
from shared.codec import decode, encode
from tests.reliability.fuzzing import _envelope, _header_of

NUMERIC = (int, float)
# Published messages that services consume: as untrusted as a request.
CONSUMED = ("Frame", "MapInfo", "JobEvent", "TourRecording")


@dataclass(frozen=True)
class Leaf:
    path: str  # e.g. "options.goal_m[]" ([] = any element, {} = any dict value/key)
    kind: type
    lower: float | None
    upper: float | None


def _bounds(metadata: list) -> tuple[float | None, float | None]:
    lo = hi = None
    for m in metadata:
        if isinstance(m, (at.Ge, at.Gt)):
            lo = m.ge if isinstance(m, at.Ge) else m.gt
        elif isinstance(m, (at.Le, at.Lt)):
            hi = m.le if isinstance(m, at.Le) else m.lt
        elif hasattr(m, "metadata"):  # a FieldInfo inside Annotated
            l2, h2 = _bounds(list(m.metadata))
            lo, hi = lo if l2 is None else l2, hi if h2 is None else h2
    return lo, hi


def _walk(tp: Any, path: str, metadata: list, seen: set) -> Iterator[Leaf]:
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        base, *extra = typing.get_args(tp)
        yield from _walk(base, path, [*metadata, *extra], seen)
    elif origin in (typing.Union, types.UnionType):
        for a in typing.get_args(tp):
            if a is not type(None):
                yield from _walk(a, path, metadata, seen)
    elif origin in (tuple, list):
        for a in {a for a in typing.get_args(tp) if a is not Ellipsis}:
            yield from _walk(a, path + "[]", [], seen)
    elif origin is dict:
        k, v = typing.get_args(tp)
        yield from _walk(k, path + "{key}", [], seen)
        yield from _walk(v, path + "{}", [], seen)
    elif isinstance(tp, type) and issubclass(tp, BaseModel):
        if tp in seen:
            return
        for name, f in tp.model_fields.items():
            yield from _walk(f.annotation, f"{path}.{name}" if path else name, list(f.metadata), seen | {tp})
    elif tp in NUMERIC and tp is not bool:
        lo, hi = _bounds(metadata)
        yield Leaf(path, tp, lo, hi)


def numeric_leaves(model: type[BaseModel]) -> list[Leaf]:
    return list(_walk(model, "", [], set()))


def request_schemas() -> list[type[schemas.Message]]:
    """Every request schema of the catalogue, and the published messages a service consumes."""
    names = {k.request for k in keys.CATALOGUE if k.request} | set(CONSUMED)
    return [getattr(schemas, n) for n in sorted(names)]


# --- well-formed bad values -------------------------------------------------------------------------

BAD_FLOATS = (float("nan"), float("inf"), float("-inf"), 1e300, -1e300)
BAD_INTS = (2**62, -(2**62))


def _paths(data: Any, path: str = "") -> Iterator[tuple[str, tuple]]:
    """(schema-style path, concrete location) of every number in a dumped message."""
    if isinstance(data, bool):
        return
    if isinstance(data, NUMERIC):
        yield path, ()
    elif isinstance(data, dict):
        if set(data) == {"__nd__"}:
            return  # an array: checked by the array validators, not here
        for k, v in data.items():
            for p, loc in _paths(v, f"{path}.{k}" if path else str(k)):
                yield p, (k, *loc)
    elif isinstance(data, (list, tuple)):
        for i, v in enumerate(data):
            for p, loc in _paths(v, path + "[]"):
                yield p, (i, *loc)


def _set(data: Any, loc: tuple, value: Any) -> None:
    for k in loc[:-1]:
        data = data[k]
    data[loc[-1]] = value


def bad_value_payloads(sample: schemas.Message) -> Iterator[tuple[str, Any, bytes]]:
    """(path, value, payload): ``sample`` with one number replaced by a non-finite, huge or
    out-of-range value, encoded as a well-formed envelope of the sample's schema."""
    payload = encode(sample)
    header, head_end = _header_of(payload)
    arrays = payload[-(-head_end // 8) * 8:]  # the array region (offsets are relative to its start)
    for path, loc in _paths(header["d"]):
        holder = header["d"]
        for k in loc[:-1]:
            holder = holder[k]
        values = BAD_INTS + BAD_FLOATS[1:3] if isinstance(holder[loc[-1]], int) else BAD_FLOATS
        for value in values:
            data = msgpack.unpackb(msgpack.packb(header["d"], use_bin_type=True), raw=False, strict_map_key=False)
            _set(data, loc, value)
            head = _envelope({**header, "d": data})
            yield path, value, head + b"\0" * (-len(head) % 8) + arrays


def samples(map_id: str = "m", panorama: schemas.Panorama | None = None) -> dict[str, schemas.Message]:
    """A valid message of every request (and consumed) schema that carries numbers."""
    import numpy as np

    S = schemas
    pose = S.Pose(position_m=(1.0, 2.0, 0.0), heading_rad=0.5)
    cam = S.CameraIntrinsics(width_px=16, height_px=16, hfov_deg=90.0)
    if panorama is None:
        v = 12
        panorama = S.Panorama(pose=pose, camera=cam, headings_rad=np.zeros(v), rgb=np.zeros((v, 16, 16, 3), np.uint8),
                              depth_m=np.ones((v, 16, 16), np.float32), timestamp_s=1.0)
    cand = S.Candidate(index=0, dx_m=0.5, dy_m=0.25, angle_rad=0.1, distance_m=0.6, score=0.5)
    tour = S.TourRecording(exploration_id="x", recording="r", region=1, start_pose=pose, frame_count=3)
    out: list[S.Message] = [
        S.ObserveRequest(camera=cam), S.MoveRequest(dx_m=0.5, dy_m=-0.25), S.TurnRequest(angle_rad=0.3),
        S.ResetRequest(pose=pose), S.GeodesicRequest(start_m=(1.0, 2.0, 0.0), goal_m=(2.0, 1.0, 0.0)),
        S.SceneViewsRequest(views=[S.ViewPose(position_m=(1.0, 2.0, 0.0), heading_rad=0.2, pitch_rad=0.1)], camera=cam),
        S.RecordRequest(recording="fuzz-rec", start=False, rate_hz=5.0, max_width_px=64), panorama,
        S.ExplorationRequest(exploration_id="x-fuzz", map_id=map_id, max_steps=5, options={"k": 1.5}),
        S.MapRequest(map_id=map_id, version=1), S.MapChunkRequest(map_id=map_id, version=1, index=0, max_points=1000),
        # An abort: valid, and sending it to the real store changes nothing.
        S.MapImportRequest(map_id="fuzz-import", filename="f.ply", upload_id="up-fuzz", offset=5, abort=True, last=False),
        S.BuildMapRequest(build_id="b-fuzz", exploration_id="x-fuzz", map_id="fuzz-build", recordings=[tour], label_names={1: "wall"},
                          options={"k": 1.5},
                          navigation=S.NavGraph(nodes=[S.NavNode(node_id="n0", position_m=(1.0, 2.0, 0.0), visited=True,
                                                                 region=1, floor=0),
                                                       S.NavNode(node_id="n1", position_m=(1.5, 2.0, 0.0), visited=False)],
                                                edges=[S.NavEdge(a="n0", b="n1", length_m=0.5)]),
                          pose_graph=S.PoseGraphSummary(panoramas=3, scan_edges=2, edges_rejected=1, loop_closures_accepted=1,
                                                        loop_closures_rejected=1, applied=True, panoramas_corrected=2,
                                                        median_correction_m=0.02, max_correction_m=0.05,
                                                        max_correction_deg=1.0)),
        S.SceneGraphRequest(map_id=map_id, version=1),
        S.RenderRequest(map_id=map_id, views=[S.ViewPose(position_m=(1.0, 2.0, 0.0), heading_rad=0.2, pitch_rad=0.1)],
                        camera=cam, camera_height_m=1.2),
        S.SpatialMapRequest(map_id=map_id, pose=pose, candidates=[cand], size_px=64, radius_m=5.0),
        S.MissionRequest(mission_id="m-fuzz", instruction="Walk to the kitchen.", map_id=map_id,
                         options=S.MissionOptions(max_steps=2, anticipation_hfov_deg=90.0, goal_m=(1.0, 1.0, 0.0),
                                                  reference_path_m=[(1.0, 1.0, 0.0)], start_pose=pose, seed=1,
                                                  policy_config={"temperature": 0.5})),
        S.Frame(index=0, timestamp_s=1.0, pose=pose, pitch_rad=0.1, imu_heading_rad=0.2, camera=cam,
                rgb=np.zeros((16, 16, 3), np.uint8)),
        S.MapInfo(map_id=map_id, version=1, point_count=5, bounds_min_m=(0.0, 0.0, 0.0), bounds_max_m=(1.0, 1.0, 1.0),
                  label_names={1: "wall"}, regions=1, scale_factors=[1.0], timings_s={"t": 1.0}, created_s=1.0,
                  drift_correction=S.DriftCorrection(
                      applied=True, method="sequential", regions=True, regions_corrected=1, max_correction_m=0.1,
                      max_correction_deg=1.0, per_region=[S.RegionDriftCorrection(
                          region=0, correction_m=0.1, correction_deg=1.0, fitness=0.5, rmse_m=0.01,
                          frames_registered=1, frames_fallback=1)])),
        tour,
    ]
    out_by_name = {m.SCHEMA: m for m in out}
    # Job events: one per typed payload that carries numbers.
    usage = S.UsageData(calls=1, prompt_tokens=10, completion_tokens=5, cost_usd=0.01, reasks=1, fallbacks=1,
                        cache_hits=1)
    metrics = S.EpisodeMetricsData(ne_m=1.0, success=True, oracle_success=True, oracle_ne_m=0.5, tl_m=3.0, spl=0.5,
                                   ndtw=0.5, sdtw=0.5, shortest_m=2.0, stop_called=True, steps=3, goal_reachable=True)
    R, F = S.JobState.RUNNING, S.JobState.SUCCEEDED
    K = S.JobEventKind
    events = {
        "JobEvent": (K.STEP, R, S.MissionStep(
            pose=pose, candidates=[cand], usage=usage, timings_s={"policy": 0.1},
            decision=S.Decision(candidate_index=0, kind=S.CandidateKind.WAYPOINT, prompt_tokens=3,
                                completion_tokens=2, cost_usd=0.01))),
        "JobEvent:started": (K.STARTED, R, S.MissionStarted(
            pose=pose, instruction="go", map_id=map_id, options=out_by_name["MissionRequest"].options)),
        "JobEvent:finished": (K.FINISHED, F, S.MissionFinished(
            stop_called=True, steps=3, trajectory_m=[(1.0, 2.0, 0.0)], metrics=metrics, usage=usage,
            step_latency_s=[0.1])),
        "JobEvent:progress": (K.PROGRESS, R, S.ExplorationProgress(
            stage="touring", progress=0.5, region=1, frames=3, nodes=4, regions=2, timings_s={"t": 1.0})),
        "JobEvent:explored": (K.FINISHED, F, S.ExplorationFinished(
            map_id=map_id, version=1, points=5, regions=1, skipped_regions=[2], nodes=3, wall_s=1.0,
            timings_s={"t": 1.0})),
    }
    for name, (kind, state, data) in events.items():
        out_by_name[name] = S.JobEvent(job_id="m-fuzz", seq=0, kind=kind, state=state, step=1,
                                           timestamp_s=1.0, data=data)
    return out_by_name
