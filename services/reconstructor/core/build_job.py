"""The map-build job: recorded tours in, a stored and announced map version out (paper 4.2 end to end).

A job body for :class:`shared.jobs.JobRunner`, written against two ports - where the frames come from
and what to do with a stored map - so the same code runs behind the bus and in-process. It reports
its progress (collecting frames, each region reconstructed, storing) as typed events; a build that
cannot produce a map fails with the cause, and the frames it consumed are released either way.

A cancel is seen while frames are awaited (every ``_CANCEL_POLL_S``), after each region and before
storing: a cancelled build stores nothing (the store's save is atomic, and is never begun after one).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Protocol

from shared.jobs import JobContext, JobEnd
from shared.schemas import BuildMapRequest, Frame, JobState, MapBuildFinished, MapBuildProgress, MapInfo

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
        for i, rec in enumerate(req.recordings):
            ctx.check_cancelled()
            got = _collect(ctx, frames, rec.recording, rec.frame_count, frames_timeout_s)
            if len(got) < rec.frame_count:
                log.warning("recording %s: %d of %d frames arrived", rec.recording, len(got), rec.frame_count)
            regions.append(region_from_frames(rec.region, rec.start_pose, got))
            ctx.progress(MapBuildProgress(stage="collecting", progress=0.1 * (i + 1) / n, region=rec.region, regions=n,
                                          message=f"region {rec.region}: {len(got)} of {rec.frame_count} frames"))

        def on_region(k: int, total: int, rep: RegionReport) -> None:
            ctx.check_cancelled()
            what = f"left out ({rep.error})" if rep.error else f"{rep.points_world:,} points"
            ctx.progress(MapBuildProgress(stage="reconstructing", progress=0.1 + 0.8 * (k + 1) / total,
                                          region=rep.region, regions=total,
                                          message=f"region {rep.region} ({k + 1}/{total}): {what}"))

        with Reconstructor(config) as recon:
            built = recon.build(regions, req.label_names, on_region)
        ctx.check_cancelled()
        ctx.progress(MapBuildProgress(stage="storing", progress=0.95, regions=n,
                                      message=f"storing {len(built.cloud):,} points"))
        info = store.save(req.map_id, built.cloud, source=req.source or f"exploration {req.exploration_id}",
                          regions=len(built.regions), scale_factors=built.scale_factors,
                          timings_s=built.timings_s, details=built.details(), navigation=req.navigation,
                          drift_correction=built.drift_summary())
    finally:
        for rec in req.recordings:
            frames.drop(rec.recording)
    announce(info)
    return JobEnd(JobState.SUCCEEDED, MapBuildFinished(info=info))


def _collect(ctx: JobContext, frames: FrameSource, recording: str, count: int, timeout_s: float) -> list[Frame]:
    """The recording's frames once ``count`` arrived (what there is at the deadline), waited for in
    slices so that a cancel is not held up by frames that never come (their robot stopped, say)."""
    end = time.monotonic() + timeout_s
    while True:
        got = frames.wait(recording, count, min(_CANCEL_POLL_S, max(0.0, end - time.monotonic())))
        if len(got) >= count or time.monotonic() >= end:
            return got
        ctx.check_cancelled()
