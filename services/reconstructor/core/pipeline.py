"""Physically grounded reconstruction end to end: regional clouds -> metric alignment -> global
integration -> one merged, voxel-downsampled map (paper Section 4.2). The map keeps labels and view
directions (where each point was seen from) when every region's cloud has them. A backend may fuse the
whole map at once instead (``RegionalReconstructor.fuse_map``: the RGB-D backend's one TSDF volume of
every noisy-depth region's frames); the regions it stands for then give only their reports."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.cloud import PointCloud, view_dirs_unit
from shared.geometry import DEFAULT_CAMERA_HEIGHT_M
from shared.schemas import DriftCorrection, RegionDriftCorrection

from .align import AlignmentConfig, AlignmentReport, MetricAligner, to_world
from .depth import DEFAULT_METRIC_DEPTH, METRIC_DEPTH, MetricDepth
from .errors import AlignmentError, EmptyRecordingError, ReconstructorError
from .frames import RecordingLike, RegionInput, region_from_recording
from .regional import (DEFAULT_RECONSTRUCTOR, RECONSTRUCTORS, MapProgressFn, RegionalCloud,
                       RegionalReconstructor)
from .registration import (RegistrationConfig, register_frames, register_moves, register_regions, register_stands,
                           se2_params, transform_cloud, transform_region)
from .voxel import voxel_downsample

log = logging.getLogger(__name__)


class ReconstructionConfig(BaseModel):
    """Everything a map build takes; the defaults run offline on a CPU with RGB-D frames."""

    model_config = ConfigDict(extra="forbid")

    backend: str = DEFAULT_RECONSTRUCTOR
    backend_config: dict[str, Any] = Field(default_factory=dict)
    metric_depth: str = DEFAULT_METRIC_DEPTH
    metric_depth_config: dict[str, Any] = Field(default_factory=dict)
    alignment: AlignmentConfig = Field(default_factory=AlignmentConfig)
    merge_voxel_m: float = Field(0.03, gt=0.0, le=1.0)
    camera_height_m: float = Field(DEFAULT_CAMERA_HEIGHT_M, gt=0.0, le=3.0)
    # A region that cannot be reconstructed or aligned is left out (and reported) instead of
    # failing the whole map; off by default so that problems are loud.
    skip_failed_regions: bool = False
    # Drift correction (frames within a region, regions to each other); off unless asked for.
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)


@dataclass
class RegionReport:
    """Per-region outcome of a build (JSON-friendly via :meth:`as_dict`)."""

    region: int
    backend: str
    frames: int
    points_local: int
    points_world: int
    metric: bool
    alignment: AlignmentReport | None
    timings_s: dict[str, float]
    true_scale: float | None = None
    error: str | None = None
    # Drift correction of this region: frames registered / fell back, the region's correction.
    registration: dict | None = None

    @property
    def scale_error(self) -> float | None:
        """``|delta * s_true - 1|`` where the backend knows its true scale (mono-sim)."""
        if self.true_scale is None or self.alignment is None:
            return None
        return abs(self.alignment.delta_applied * self.true_scale - 1.0)

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "alignment"}
        d["alignment"] = None if self.alignment is None else self.alignment.as_dict()
        d["scale_error"] = self.scale_error
        return d


@dataclass
class MapBuild:
    """A reconstructed map: the merged world cloud and how it was made."""

    cloud: PointCloud
    regions: list[RegionReport]
    timings_s: dict[str, float]
    config: ReconstructionConfig
    regional_clouds: list[PointCloud] = field(default_factory=list)  # world frame, before the merge
    drift_correction: dict = field(default_factory=lambda: {"applied": False})
    # The regions whose frames the backend fused into the map's one volume (fuse_map): their own clouds are
    # not in the map.
    fused_regions: list[int] = field(default_factory=list)

    @property
    def scale_factors(self) -> list[float]:
        return [r.alignment.delta_applied for r in self.regions if r.alignment is not None]

    @property
    def frames(self) -> int:
        return sum(r.frames for r in self.regions)

    def drift_summary(self) -> DriftCorrection:
        """The typed record of the drift correction that goes into the map's :class:`MapInfo`."""
        d = self.drift_correction
        per = []
        for r in self.regions:
            reg = r.registration or {}
            fr, rg, st = reg.get("frames") or {}, reg.get("region") or {}, reg.get("stands") or {}
            mv = reg.get("moves") or {}
            if not (fr or rg or st.get("adjusted") or mv.get("adjusted")):  # stands, drives left as they were: none
                continue
            per.append(RegionDriftCorrection(
                region=r.region, anchor=bool(rg.get("anchor", False)), fell_back=bool(rg.get("fell_back", False)),
                reason=str(rg.get("reason", ""))[:64],
                correction_m=float(rg.get("correction_m", fr.get("correction_m", mv.get("max_correction_m", 0.0)))),
                correction_deg=min(180.0, float(rg.get("correction_deg", fr.get("correction_deg", max(
                    st.get("max_correction_deg", 0.0), mv.get("max_correction_deg", 0.0)))))),
                fitness=rg.get("fitness"), rmse_m=rg.get("rmse_m"),
                frames_registered=int(fr.get("registered", 0)) + int(st.get("frames_adjusted", 0))
                + int(mv.get("frames_adjusted", 0)),
                frames_fallback=int(fr.get("fallback", 0))))
        moved = [p for p in per if p.correction_m > 0.0 or p.correction_deg > 0.0]
        return DriftCorrection(
            applied=bool(d.get("applied")), method=str(d.get("method", "")), frames=bool(d.get("frames")),
            regions=bool(d.get("regions")), regions_corrected=len(moved),
            regions_fallback=sum(p.fell_back for p in per),
            max_correction_m=max((p.correction_m for p in per), default=0.0),
            max_correction_deg=max((p.correction_deg for p in per), default=0.0),
            loop_closures_accepted=int(d.get("loop_closures_accepted", 0)),
            loop_closures_rejected=int(d.get("loop_closures_rejected", 0)), per_region=per)

    def details(self) -> dict:
        """Metadata for the map store (regions, alignment, timings, config)."""
        return {
            "backend": self.config.backend,
            "metric_depth": self.config.metric_depth,
            "frames": self.frames,
            "regions": [r.as_dict() for r in self.regions],
            # Says plainly whether the map was corrected for drift, and how (issue 33).
            "drift_correction": self.drift_correction,
            "fused_as_one_volume": list(self.fused_regions),
            "config": self.config.model_dump(mode="json"),
        }


ProgressFn = Callable[[int, int, RegionReport], None]


class Reconstructor:
    """Builds maps from region recordings with the configured backends (created once, reused)."""

    def __init__(
        self,
        config: ReconstructionConfig | None = None,
        backend: RegionalReconstructor | None = None,
        depth: MetricDepth | None = None,
    ):
        self.config = cfg = config or ReconstructionConfig()
        self.backend = backend or RECONSTRUCTORS.create(cfg.backend, cfg.backend_config or None)
        self.depth = depth or METRIC_DEPTH.create(cfg.metric_depth, cfg.metric_depth_config or None)
        self.aligner = MetricAligner(cfg.alignment, self.depth)

    def close(self) -> None:
        self.backend.close()

    def __enter__(self) -> Reconstructor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def build_from_recordings(
        self, recordings: Sequence[RecordingLike], label_names: dict[int, str] | None = None,
        on_region: ProgressFn | None = None, on_map: MapProgressFn | None = None,
    ) -> MapBuild:
        """Convenience for the mapper's ``RegionRecording`` list (validates every frame first)."""
        regions = [region_from_recording(r, self.config.camera_height_m) for r in recordings]
        return self.build(regions, label_names, on_region, on_map)

    def build(
        self, regions: Sequence[RegionInput], label_names: dict[int, str] | None = None,
        on_region: ProgressFn | None = None, on_map: MapProgressFn | None = None,
    ) -> MapBuild:
        """Reconstruct, align and integrate every region; merge into one map. ``on_region`` after each
        region; ``on_map`` after each region the backend's map-wide fusion took in (``fuse_map``)."""
        if not regions:
            raise EmptyRecordingError("no regions to reconstruct")
        t_start = time.perf_counter()
        totals = {"regional": 0.0, "align": 0.0, "integrate": 0.0}
        reports: list[RegionReport] = []
        clouds: list[PointCloud] = []
        placed: list[int] = []  # index into reports of each cloud
        inputs: list[RegionInput] = []  # each cloud's region, its images as its stages registered them
        cfg = self.config.registration
        # A region's own stages, in this order: the stands' headings, then the drives between them (the
        # stands' frames hold the drives' ends), then the frames' ICP; each recorded under its name.
        stages = (("stands", cfg.stands.enabled, lambda images: register_stands(images, cfg.stands, cfg.threads)),
                  ("moves", cfg.moves.enabled,
                   lambda images: register_moves(images, cfg.moves, cfg.stands, cfg.threads)),
                  ("frames", cfg.frames.enabled, lambda images: register_frames(images, cfg.frames)))
        for k, region in enumerate(regions):
            stage_reports = {}
            depth = self.backend.metric and all(im.depth_m is not None for im in region.images)
            for name, enabled, run in stages:
                if enabled and depth:
                    t0 = time.perf_counter()
                    images, stage_reports[name] = run(region.images)
                    region = replace(region, images=images)
                    totals[f"register_{name}"] = totals.get(f"register_{name}", 0.0) + time.perf_counter() - t0
            try:
                rep, world = self._one(region, label_names, totals)
                rep.registration = {name: r.as_dict() for name, r in stage_reports.items()} or None
            except ReconstructorError as exc:
                if not self.config.skip_failed_regions:
                    raise
                log.warning("region %d left out: %s", region.region, exc)
                rep = RegionReport(region.region, self.backend.name, len(region.images), 0, 0,
                                   self.backend.metric, None, {}, error=f"{type(exc).__name__}: {exc}")
                world = None
            reports.append(rep)
            if world is not None:
                clouds.append(world)
                placed.append(len(reports) - 1)
                inputs.append(region)
            if on_region is not None:
                on_region(k, len(regions), rep)
        if not clouds:
            raise EmptyRecordingError("no region could be reconstructed")
        # Stands whose headings moved (a noise-free robot's never do: its map says it was not corrected).
        stands = sum(((r.registration or {}).get("stands") or {}).get("adjusted", 0) for r in reports)
        drives = sum(((r.registration or {}).get("moves") or {}).get("adjusted", 0) for r in reports)
        drift = {"applied": False, "frames": cfg.frames.enabled, "regions": False, "stands_adjusted": stands,
                 "drives_adjusted": drives}
        rcfg = cfg.regions
        if rcfg.enabled and len(clouds) > 1:
            views = [None if c.view_dirs is None else view_dirs_unit(c.view_dirs) for c in clouds]
            graph = register_regions([c.xyz for c in clouds], rcfg, views)
            clouds = [transform_cloud(c, x) for c, x in zip(clouds, graph.corrections)]
            inputs = [transform_region(r, x) for r, x in zip(inputs, graph.corrections)]
            ids = [reports[i].region for i in placed]
            for j, (i, x) in enumerate(zip(placed, graph.corrections)):
                cx, cy, cyaw = se2_params(x)
                reg = reports[i].registration or {}
                reg["region"] = {"correction_m": math.hypot(cx, cy), "correction_deg": abs(math.degrees(cyaw)),
                                 "shift_m": [cx, cy], "turn_deg": math.degrees(cyaw),
                                 **(graph.regions[j] if j < len(graph.regions) else {})}
                reports[i].registration = reg
            loops = [e for e in graph.edges if e.loop]
            drift.update(regions=True, method=graph.method, pairs_tried=graph.pairs_tried, pairs_failed=dict(graph.pairs_failed),
                         edges=[e.as_dict(ids) for e in graph.edges],
                         loop_closures_accepted=sum(e.accepted for e in loops),
                         loop_closures_rejected=sum(not e.accepted for e in loops))
            totals["register_regions"] = graph.timings_s
        drift["applied"] = bool(drift["frames"] or drift["regions"] or drift["stands_adjusted"]
                                or drift["drives_adjusted"])
        t0 = time.perf_counter()
        # A backend that fuses the whole map at once (RgbdConfig.tsdf_scope) replaces the clouds of the
        # regions it fused; the others' clouds stay.
        parts, ids = clouds, []
        fused = self.backend.fuse_map(inputs, label_names, on_map)
        if fused is not None:
            cloud, ids = fused
            own = set(ids)
            parts = [cloud] + [c for c, r in zip(clouds, inputs) if r.region not in own]
            totals["fuse_map"] = time.perf_counter() - t0
            t0 = time.perf_counter()
        merged = voxel_downsample(PointCloud.concatenate(parts), self.config.merge_voxel_m)
        if label_names:
            merged.label_names = dict(label_names)
        totals["merge"] = time.perf_counter() - t0
        totals["total"] = time.perf_counter() - t_start
        log.info("map: %d regions, %d points, %.2f s", len(clouds), len(merged), totals["total"])
        return MapBuild(merged, reports, totals, self.config, clouds, drift, list(ids))

    def _one(self, region: RegionInput, label_names, totals) -> tuple[RegionReport, PointCloud]:
        t0 = time.perf_counter()
        regional: RegionalCloud = self.backend.reconstruct(region, label_names)
        t1 = time.perf_counter()
        note = None
        try:
            report = self.aligner.align(region, regional)
        except AlignmentError as exc:
            if not regional.metric:
                raise
            # A metric cloud needs no grounding (delta is only measured, never applied): when the
            # check cannot run - the start view faces a wall too close to render, say - the
            # region is integrated as it is, and the report says why it was not checked.
            log.warning("region %d: alignment check skipped: %s", region.region, exc)
            note = f"alignment check skipped: {exc}"
            report = AlignmentReport(region.region, -1, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0, self.depth.name,
                                     0.0, 0.0, 0.0)
        t2 = time.perf_counter()
        world = to_world(regional, report, region)
        t3 = time.perf_counter()
        totals["regional"] += t1 - t0
        totals["align"] += t2 - t1
        totals["integrate"] += t3 - t2
        rep = RegionReport(
            region=region.region, backend=regional.backend, frames=regional.frames_used,
            points_local=len(regional.cloud), points_world=len(world), metric=regional.metric,
            alignment=report,
            timings_s={**regional.timings_s, "regional": t1 - t0, "align": t2 - t1, "integrate": t3 - t2},
            true_scale=regional.true_scale,
            error=note,
        )
        if rep.scale_error is not None:
            log.info("region %d: scale error %.2f %%", region.region, 100.0 * rep.scale_error)
        return rep, world


def chamfer(a_xyz: np.ndarray, b_xyz: np.ndarray) -> dict[str, float]:
    """Nearest-neighbour distances both ways: accuracy (a -> b), completeness (b -> a), Chamfer mean."""
    from scipy.spatial import cKDTree

    if len(a_xyz) == 0 or len(b_xyz) == 0:
        return {"accuracy_mean_m": math.inf, "completeness_mean_m": math.inf, "chamfer_m": math.inf}
    d_ab, _ = cKDTree(b_xyz).query(a_xyz, workers=-1)
    d_ba, _ = cKDTree(a_xyz).query(b_xyz, workers=-1)
    return {
        "accuracy_mean_m": float(d_ab.mean()),
        "accuracy_p95_m": float(np.percentile(d_ab, 95)),
        "completeness_mean_m": float(d_ba.mean()),
        "completeness_p95_m": float(np.percentile(d_ba, 95)),
        "chamfer_m": float(0.5 * (d_ab.mean() + d_ba.mean())),
        "chamfer_p95_m": float(0.5 * (np.percentile(d_ab, 95) + np.percentile(d_ba, 95))),
    }
