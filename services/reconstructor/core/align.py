"""Cross-modal metric alignment and global pose integration (paper 4.2).

For a regional cloud: render a forward-facing RGB image and depth map at the local origin with the
renderer's Gaussian splatting; among the video frames at the start of the path, pick the one whose
RGB is most similar (SSIM averaged over the three channels); take that frame's metric depth from a
metric-depth backend; the scale is ``delta = mean(metric / rendered)`` over the pixels where neither
has a hole (the median is reported too).

SSIM alone cannot tell apart views of a plain wall a few degrees apart (they tie), and a frame turned
away from the rendered view measures other surfaces: its ratio is not the scale. So the best frames by
SSIM are checked by geometry (``verify_top_k``): at the right frame ``metric / rendered`` is one
constant up to noise, at a turned one it spreads, and the frame whose log ratio spreads least (median
absolute deviation, scale-free) is taken. On generated:1:area=60 (mono-sim, seed 0) region 2 tied
frames 15 deg apart at SSIM 0.450 and the first one, the wrong one, gave a 10.3 % scale error (its
spread 0.088 against 0.0065 at the right frame). The matched frame's heading relative to the start heading
is ``theta_t``. Then ``W_global = R_z(theta0 + theta_t) (delta W_local) + p0``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field
from skimage.metrics import structural_similarity

from shared.cloud import PointCloud, rotate_view_dirs
from shared.geometry import camera_rotation, rot_z, wrap_angle
from libs.pointrender import RENDERERS, IndexedCloud  # the renderer service's splatting, in-process
from shared.registry import BackendConfig

from .depth import MetricDepth
from .errors import AlignmentError
from .frames import PosedImage, RegionInput
from .regional import RegionalCloud

log = logging.getLogger(__name__)

# The forward render must not depend on the cloud's unknown scale: relative occlusion tolerance
# only, and clip planes far outside any scale a network could produce. The paper's 3x3 splat:
# the visibility mode's gap limits and tolerances are in metres, which this cloud does not have.
_SCALE_FREE_SPLAT = {
    "mode": "paper", "near_m": 1e-4, "far_m": 1e5, "depth_tolerance_m": 0.0, "depth_tolerance_rel": 0.05,
    "lod_points_per_px": None,
}


class AlignmentConfig(BackendConfig):
    """How the forward view is rendered, matched and turned into a scale."""

    renderer: str = "numpy"
    renderer_config: dict = Field(default_factory=dict)  # overrides of the scale-free splat settings
    match_radius_m: float = Field(0.3, gt=0.0)  # candidate frames: camera this close to the start camera
    match_window: int = Field(400, ge=1)  # ... among the first this many frames of the recording
    max_pitch_deg: float = Field(10.0, ge=0.0, le=90.0)  # ... and about level, like the render
    # The best frames by SSIM (distinct views only) whose metric depth is read and whose ratio spread
    # picks the match (see the module docstring); 1 is SSIM alone, the paper's rule. Each checked frame
    # costs one metric-depth call (a network pass with depth-anything-v2).
    verify_top_k: int = Field(8, ge=1, le=64)
    statistic: Literal["mean", "median"] = "mean"  # the paper's delta is the mean ratio
    min_valid_fraction: float = Field(0.02, gt=0.0, le=1.0)
    # Omega also leaves out pixels at depth discontinuities and beside holes, where a splat or a
    # sensor mixes two surfaces: their ratio measures the mix, not the scale. A pixel is an edge
    # when its 3x3 neighbourhood's max/min depth exceeds 1 + this (scale-free); None keeps them.
    edge_rel: float | None = Field(0.1, gt=0.0)
    # "auto": apply theta_t only to non-metric clouds, whose frame orientation is unknown; a metric
    # backend already works in the start pose's frame (theta_t is still measured and reported).
    use_matched_heading: Literal["auto", "always", "never"] = "auto"


@dataclass
class AlignmentReport:
    """What alignment found for one region (JSON-friendly via :meth:`as_dict`)."""

    region: int
    matched_index: int  # Frame.index of the matched frame
    ssim: float
    theta_t_rad: float
    theta_applied_rad: float
    delta_mean: float
    delta_median: float
    delta_applied: float
    valid_fraction: float
    candidates: int
    metric_backend: str
    render_s: float
    match_s: float
    depth_s: float
    ratio_spread: float = 0.0  # median absolute deviation of log(metric / rendered) at the matched frame
    verified: int = 0  # frames whose ratio spread was measured (the best by SSIM, distinct views)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class MetricAligner:
    """Renders, matches and scales regional clouds; one instance serves many regions."""

    def __init__(self, config: AlignmentConfig | None, depth: MetricDepth):
        self.config = cfg = config or AlignmentConfig()
        self.depth = depth
        self.renderer = RENDERERS.create(cfg.renderer, {**_SCALE_FREE_SPLAT, **cfg.renderer_config})

    def candidates(self, region: RegionInput, pitch_rad: float = 0.0) -> list[PosedImage]:
        """Frames at the start of the path (the paper's frames 'at the start position') pitched
        like the forward render (level for robot recordings)."""
        cfg = self.config
        cam0 = region.start_pose.xyz + np.array([0.0, 0.0, region.camera_height_m])
        max_pitch = math.radians(cfg.max_pitch_deg)
        out = [
            im for im in region.images[: cfg.match_window]
            if np.linalg.norm(im.position_m - cam0) <= cfg.match_radius_m
            and abs(im.pitch_rad - pitch_rad) <= max_pitch
        ]
        if not out:
            raise AlignmentError(
                f"region {region.region}: no level frame within {cfg.match_radius_m} m of the path start"
            )
        return out

    def align(self, region: RegionInput, regional: RegionalCloud) -> AlignmentReport:
        cfg = self.config
        if len(regional.cloud) == 0:
            raise AlignmentError(f"region {region.region}: empty regional cloud")
        cands = self.candidates(region, regional.camera_pitch_rad)
        cam = cands[0].camera
        cands = [im for im in cands if im.camera == cam]
        t0 = time.perf_counter()
        view = self.forward_view(regional, cam)
        rgb_f, depth_f, hole_f = view.rgb[0], view.depth_m[0], view.hole_mask[0]
        t1 = time.perf_counter()
        scores = np.array([_ssim_rgb(rgb_f, im.rgb) for im in cands])
        order = _distinct_views(cands, np.argsort(-scores, kind="stable"))[: cfg.verify_top_k]
        t2 = time.perf_counter()
        best = None  # (spread, candidate index, ratio, valid fraction)
        frac_seen = 0.0
        for i in order:
            ratio, frac = self._ratio(self.depth.depth(cands[i]), depth_f, hole_f)
            frac_seen = max(frac_seen, frac)
            if ratio is None:
                continue
            log_r = np.log(ratio)
            spread = float(np.median(np.abs(log_r - np.median(log_r))))
            if best is None or spread < best[0]:
                best = (spread, i, ratio, frac)
        t3 = time.perf_counter()
        if best is None:
            raise AlignmentError(
                f"region {region.region}: only {frac_seen:.1%} of the forward view has both rendered and metric depth"
            )
        spread, i, ratio, frac = best
        matched = cands[i]
        d_mean, d_median = float(ratio.mean()), float(np.median(ratio))
        if regional.metric:
            applied = 1.0
        else:
            applied = d_mean if cfg.statistic == "mean" else d_median
        theta_t = float(wrap_angle(matched.imu_heading_rad - region.images[0].imu_heading_rad))
        use = cfg.use_matched_heading == "always" or (cfg.use_matched_heading == "auto" and not regional.metric)
        rep = AlignmentReport(
            region=region.region, matched_index=matched.index, ssim=float(scores[i]),
            theta_t_rad=theta_t, theta_applied_rad=theta_t if use else 0.0,
            delta_mean=d_mean, delta_median=d_median, delta_applied=float(applied),
            valid_fraction=frac, candidates=len(cands), ratio_spread=spread, verified=len(order),
            metric_backend=self.depth.name,
            render_s=t1 - t0, match_s=t2 - t1, depth_s=t3 - t2,
        )
        log.info(
            "region %d: matched frame %d (ssim %.3f, theta_t %.1f deg), delta mean %.4f median %.4f",
            rep.region, rep.matched_index, rep.ssim, math.degrees(theta_t), d_mean, d_median,
        )
        return rep

    def _ratio(self, metric: np.ndarray, depth_f: np.ndarray, hole_f: np.ndarray) -> tuple[np.ndarray | None, float]:
        """metric / rendered over Omega (both valid, no edge), float64; None when too few pixels."""
        cfg = self.config
        valid = (~hole_f) & (depth_f > 0) & np.isfinite(metric) & (metric > 0)
        if cfg.edge_rel is not None:
            valid &= ~_edges(np.where(valid, depth_f, 0.0), cfg.edge_rel)
            valid &= ~_edges(np.where(valid, metric, 0.0), cfg.edge_rel)
        frac = float(valid.mean())
        if frac < cfg.min_valid_fraction or valid.sum() < 16:
            return None, frac
        return metric[valid].astype(np.float64) / depth_f[valid].astype(np.float64), frac

    def forward_view(self, regional: RegionalCloud, camera):
        """The forward render at the local origin (for pictures and debugging)."""
        index = IndexedCloud(regional.cloud, block_m=_block_size(regional.cloud))
        wfc = np.eye(4)
        wfc[:3, :3] = camera_rotation(0.0, regional.camera_pitch_rad)
        wfc[:3, 3] = regional.camera_origin_m
        return self.renderer.render_poses(index, [wfc], camera, with_labels=False)


def _distinct_views(cands: list[PosedImage], order: np.ndarray) -> list[int]:
    """``order`` without repeats of one view: a robot standing still records the same pose many times,
    and checking a view twice would spend a metric-depth call on nothing."""
    seen, out = [], []
    for i in order:
        t = cands[int(i)].world_from_camera
        if any(np.allclose(t, s, atol=1e-6) for s in seen):
            continue
        seen.append(t)
        out.append(int(i))
    return out


def _edges(depth: np.ndarray, rel: float) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood spans a depth ratio above ``1 + rel`` or touches a hole (0)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    d = depth.astype(np.float64)
    lo = minimum_filter(d, size=3, mode="nearest")
    hi = maximum_filter(d, size=3, mode="nearest")
    return (lo <= 0) | (hi > lo * (1.0 + rel))


def _block_size(cloud: PointCloud) -> float:
    # Culling blocks follow the cloud's own (unknown) scale: about 8 blocks across its extent.
    lo, hi = cloud.bounds()
    return float(max(np.max(hi - lo) / 8.0, 1e-3))


def _ssim_rgb(a: np.ndarray, b: np.ndarray) -> float:
    """Structural similarity averaged over the three colour channels."""
    if a.shape != b.shape:
        raise AlignmentError(f"rendered view {a.shape} and frame {b.shape} differ in size")
    win = min(7, min(a.shape[:2]) // 2 * 2 - 1)
    if win < 3:
        raise AlignmentError(f"images of {a.shape[:2]} are too small for SSIM")
    return float(np.mean([
        structural_similarity(a[..., c], b[..., c], data_range=255, win_size=win) for c in range(3)
    ]))


def to_world(
    regional: RegionalCloud,
    report: AlignmentReport,
    region: RegionInput,
) -> PointCloud:
    """``W_global = R_z(theta0 + theta_t) (delta (W_local - c) + (0, 0, h)) + p0``.

    ``c`` is the forward camera's position in the regional frame: subtracting it and adding the
    metric camera height puts the floor point of the start pose at the origin, whatever the frame
    the backend used. View directions turn with ``R_z`` alone (a shift or a positive scale leaves
    them as they are).
    """
    c = regional.camera_origin_m
    h = np.array([0.0, 0.0, region.camera_height_m])
    metric = (regional.cloud.xyz.astype(np.float64) - c) * report.delta_applied + h
    r = rot_z(region.start_pose.heading_rad + report.theta_applied_rad)
    xyz = metric @ r.T + region.start_pose.xyz
    cloud = regional.cloud
    return PointCloud(xyz, cloud.rgb, cloud.labels, dict(cloud.label_names), rotate_view_dirs(cloud.view_dirs, r))
