"""The map-build job: recorded tours in, a stored and announced map version out (paper 4.2 end to end).

A job body for :class:`shared.jobs.JobRunner`, written against two ports - where the frames come from
and what to do with a stored map - so the same code runs behind the bus and in-process. It reports
its progress (collecting frames, each region reconstructed, each region fused into the map's one volume,
storing) as typed events; a build that cannot produce a map fails with the cause, and the frames it
consumed are released either way.

A cancel is seen while frames are awaited (every ``_CANCEL_POLL_S``), after each region (reconstructed,
and fused into the map's volume) and before storing: a cancelled build stores nothing (the store's save
is atomic, and is never begun after one).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Protocol

import cv2
import numpy as np

from shared.geometry import interpolate_offsets, wrap_angle
from shared.jobs import JobContext, JobEnd
from shared.schemas import (
    BuildMapRequest, DriftCorrection, Frame, JobState, MapBuildFinished, MapBuildProgress, MapInfo, OdomCorrection,
    Pose, PoseGraphSummary, TourRecording,
)

from .frames import region_from_frames
from .pipeline import ReconstructionConfig, Reconstructor, RegionReport
from .store import MapStore

log = logging.getLogger(__name__)

_CANCEL_POLL_S = 0.25  # how often a build waiting for a recording's frames looks at its cancel flag


class FrameSource(Protocol):
    """Recorded frames by recording name (the reconstructor service's buffer of ``IO_FRAMES``)."""

    def wait(self, recording: str, count: int, timeout_s: float) -> list[Frame]: ...

    def drop(self, recording: str) -> None: ...


def build_map(ctx: JobContext, req: BuildMapRequest, *, frames: FrameSource, store: MapStore,
              config: ReconstructionConfig, announce: Callable[[MapInfo], None],
              frames_timeout_s: float) -> JobEnd:
    """Collect each recording's frames, reconstruct and ground every region, store and announce the map."""
    if not req.recordings:
        raise ValueError("a build needs at least one recording")
    n = len(req.recordings)
    try:
        ctx.progress(MapBuildProgress(stage="collecting", progress=0.0, regions=n,
                                      message=f"waiting for the frames of {n} recordings"))
        regions = []
        tour_frames: dict[int, list[np.ndarray]] = {}  # region -> a few of its frames, for the labeller
        for i, rec in enumerate(req.recordings):
            ctx.check_cancelled()
            got = _collect(ctx, frames, rec.recording, rec.frame_count, frames_timeout_s)
            if len(got) < rec.frame_count:
                log.warning("recording %s: %d of %d frames arrived", rec.recording, len(got), rec.frame_count)
            start, got = in_map_frame(rec, got)
            regions.append(region_from_frames(rec.region, start, got))
            tour_frames.setdefault(rec.region, []).extend(labeller_frames(got))
            ctx.progress(MapBuildProgress(stage="collecting", progress=0.1 * (i + 1) / n, region=rec.region, regions=n,
                                          message=f"region {rec.region}: {len(got)} of {rec.frame_count} frames"))

        def on_region(k: int, total: int, rep: RegionReport) -> None:
            ctx.check_cancelled()
            what = f"left out ({rep.error})" if rep.error else f"{rep.points_world:,} points"
            ctx.progress(MapBuildProgress(stage="reconstructing", progress=0.1 + 0.8 * (k + 1) / total,
                                          region=rep.region, regions=total,
                                          message=f"region {rep.region} ({k + 1}/{total}): {what}"))

        def on_map(k: int, total: int) -> None:
            # The map's one volume (RgbdConfig.tsdf_scope "map") takes the frames of every region once
            # more after the last one: 15-17 s of a 47-52 s build on the two-floor house, so it reports too.
            ctx.check_cancelled()
            ctx.progress(MapBuildProgress(stage="fusing", progress=0.9 + 0.04 * (k + 1) / total, regions=n,
                                          message=f"map volume: {k + 1} of {total} regions fused"))

        with Reconstructor(config) as recon:
            built = recon.build(regions, req.label_names, on_region, on_map)
        ctx.check_cancelled()
        ctx.progress(MapBuildProgress(stage="storing", progress=0.95, regions=n,
                                      message=f"storing {len(built.cloud):,} points"))
        info = store.save(req.map_id, built.cloud, source=req.source or f"exploration {req.exploration_id}",
                          regions=len(built.regions), scale_factors=built.scale_factors,
                          timings_s=built.timings_s, details=built.details(), navigation=req.navigation,
                          frames={r: labeller_frames(f) for r, f in tour_frames.items()},
                          drift_correction=with_odometry(built.drift_summary(), req.recordings, req.pose_graph))
    finally:
        for rec in req.recordings:
            frames.drop(rec.recording)
    announce(info)
    return JobEnd(JobState.SUCCEEDED, MapBuildFinished(info=info))


def _corrected_pose(pose: Pose, c: OdomCorrection) -> Pose:
    x, y, z = pose.position_m
    return Pose(position_m=(x + c.dx_m, y + c.dy_m, z), heading_rad=float(wrap_angle(pose.heading_rad + c.dyaw_rad)))


def with_odometry(drift: DriftCorrection, recordings: list[TourRecording],
                  pose_graph: PoseGraphSummary | None = None) -> DriftCorrection:
    """``drift`` with the mapper's map <- odom corrections that :func:`in_map_frame` applied to the
    recordings: without this the map of a robot that has no localiser of its own would say nothing
    of the correction that placed most of it (issue 33). Per tour, the largest correction in effect;
    and the mapper's pose graph that placed them (its loop closures), when it sent one."""
    tours = [rec.odom_corrections for rec in recordings
             if any(c.dx_m or c.dy_m or c.dyaw_rad for c in rec.odom_corrections)]
    if pose_graph is not None:
        drift = drift.model_copy(update={"pose_graph": pose_graph})
    if not tours:
        return drift
    metres = [max(math.hypot(c.dx_m, c.dy_m) for c in cs) for cs in tours]
    degrees = [max(abs(math.degrees(c.dyaw_rad)) for c in cs) for cs in tours]
    return DriftCorrection.model_validate({
        **drift.model_dump(), "applied": True, "odom_regions_corrected": len(tours),
        "odom_median_correction_m": float(np.median(metres)), "odom_max_correction_m": max(metres),
        "odom_max_correction_deg": min(180.0, max(degrees))})


def in_map_frame(rec: TourRecording, frames: list[Frame]) -> tuple[Pose, list[Frame]]:
    """A recording's start pose and frames in the map frame. Robot-io publishes frames with its odometry
    poses; the mapper localised the robot meanwhile (issue 33) and sent its map <- odom corrections
    beside the recording, each from a robot time on (``map = odom + (dx, dy)``, heading + dyaw, as the
    mapper's own ``Correction``). A frame takes the latest correction at or before its timestamp (the
    first one before any), or with ``odom_corrections_interpolated`` the one interpolated in time
    between its neighbours (the mapper's pose graph placed each entry's panorama, and the drift between
    two of them grows along the way). No corrections: the recording exactly as it came (an exact robot,
    or an uncorrected mapper)."""
    if not rec.odom_corrections:
        return rec.start_pose, frames
    cs = sorted(rec.odom_corrections, key=lambda c: c.since_s)
    since = np.array([c.since_s for c in cs])
    if rec.odom_corrections_interpolated:
        at = interpolate_offsets(since, [(c.dx_m, c.dy_m, c.dyaw_rad) for c in cs], [f.timestamp_s for f in frames])
    out = []
    for k, f in enumerate(frames):
        if rec.odom_corrections_interpolated:
            c = OdomCorrection(since_s=f.timestamp_s, dx_m=at[k, 0], dy_m=at[k, 1], dyaw_rad=at[k, 2])
        else:
            c = cs[max(0, int(np.searchsorted(since, f.timestamp_s, side="right")) - 1)]
        out.append(f.model_copy(update={"pose": _corrected_pose(f.pose, c),
                                        "imu_heading_rad": float(wrap_angle(f.imu_heading_rad + c.dyaw_rad))}))
    return _corrected_pose(rec.start_pose, cs[0]), out


LABELLER_FRAMES = 8  # tour frames per region kept for the scene-graph labeller (it sends a few of them)
LABELLER_PX = 384  # ... downscaled to this longer side (the labeller's default image size)


def labeller_frames(frames, k: int = LABELLER_FRAMES, px: int = LABELLER_PX) -> list[np.ndarray]:
    """``k`` RGB frames spread evenly over a tour (not ``k`` of the same corner), each downscaled so
    that its longer side is at most ``px``: what a region costs to keep until its map is stored is
    bounded (8 x 384 x 288 x 3 bytes = 2.6 MB), whatever the camera."""
    frames = list(frames)
    if len(frames) > k:
        frames = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, k).round()]
    out = []
    for f in frames:
        rgb = f if isinstance(f, np.ndarray) else f.rgb
        scale = px / max(rgb.shape[:2])
        if scale < 1.0:
            rgb = cv2.resize(rgb, (max(1, round(rgb.shape[1] * scale)), max(1, round(rgb.shape[0] * scale))),
                             interpolation=cv2.INTER_AREA)
        out.append(np.ascontiguousarray(rgb, np.uint8))
    return out


def _collect(ctx: JobContext, frames: FrameSource, recording: str, count: int, timeout_s: float) -> list[Frame]:
    """The recording's frames once ``count`` arrived (what there is at the deadline), waited for in
    slices so that a cancel is not held up by frames that never come (their robot stopped, say)."""
    end = time.monotonic() + timeout_s
    while True:
        got = frames.wait(recording, count, min(_CANCEL_POLL_S, max(0.0, end - time.monotonic())))
        if len(got) >= count or time.monotonic() >= end:
            return got
        ctx.check_cancelled()
