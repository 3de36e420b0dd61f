"""Waypoint predictor port and the default ``geometric`` backend.

The output contract is the one of the CWP waypoint predictor (Hong et al. 2022): a heatmap of
120 angle bins (3 deg) x 12 distance bins (0.25 - 3.0 m) around the agent, reduced by non-maximum
suppression to at most 5 candidate waypoints. A learned CWP backend can register beside
``geometric`` and the mapper and planner will not notice.

Angles here are relative to the agent heading, positive to the left (counter-clockwise), bin ``k``
centred on ``k * 3 deg``. Candidates carry their offset in **world** axes (``dx_m``, ``dy_m``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from pydantic import Field, model_validator

from shared.geometry import DEFAULT_CAMERA_HEIGHT_M, wrap_angle
from shared.jit import AVAILABLE, insert_sorted, kernel, one_signature
from shared.registry import BackendConfig, Registry
from shared.schemas import Candidate, CandidateKind, Panorama

from services.mapper.core.errors import PredictorError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prediction:
    """Everything a predictor computed for one panorama (candidates plus its evidence)."""

    candidates: list[Candidate]
    heatmap: np.ndarray  # (angle_bins, distance_bins), scores in [0, 1]
    doorways: list["Doorway"]  # openings found in the obstacle profile (approach points included)
    free_distance_m: np.ndarray  # (angle_bins,) obstacle-free travel distance per angle bin
    angles_rad: np.ndarray  # (angle_bins,) bin centres relative to the heading, positive left
    distances_m: np.ndarray  # (distance_bins,) bin centres
    clearance_m: float  # the body clearance the free distances were swept with (less when boxed in)


@dataclass(frozen=True)
class Doorway:
    """An opening between two jambs, in the agent frame (x ahead, y left), metres."""

    left_m: tuple[float, float]  # the jamb at the larger angle
    right_m: tuple[float, float]
    width_m: float
    approach_m: tuple[float, float] | None  # where to stand to pass it straight; None: none reachable
    direct: bool  # the body already passes it in a straight line from here


@runtime_checkable
class WaypointPredictor(Protocol):
    """Port: candidate waypoints around the agent from its 12-view panorama."""

    def predict(self, panorama: Panorama) -> list[Candidate]:
        """At most ``max_candidates`` waypoints, best first, indices 0..k-1."""
        ...


PREDICTORS: Registry[WaypointPredictor] = Registry("waypoint predictor")
DEFAULT_PREDICTOR = "geometric"


class GeometricPredictorConfig(BackendConfig):
    """Free-space waypoint prediction from the panorama's depth.

    A pixel is an obstacle when it rises more than ``max_step_m`` above the ground the agent would
    walk on to reach it (tracked outward along each image column, so stairs and ramps whose treads
    rise by less than a step stay walkable) and lies within ``body_height_m`` above that ground.
    """

    angle_bins: int = Field(120, ge=12, le=720)
    distance_bins: int = Field(12, ge=2, le=64)
    min_distance_m: float = Field(0.25, gt=0.0)
    max_distance_m: float = Field(3.0, gt=0.0)
    max_candidates: int = Field(5, ge=1, le=32)
    camera_height_m: float = Field(DEFAULT_CAMERA_HEIGHT_M, gt=0.0, le=3.0)
    body_radius_m: float = Field(0.2, ge=0.0, le=1.0)
    clearance_margin_m: float = Field(0.05, ge=0.0, le=1.0)
    body_height_m: float = Field(1.5, gt=0.1, le=3.0)
    max_step_m: float = Field(0.22, gt=0.0, le=1.0)
    max_slope_deg: float = Field(38.0, ge=0.0, le=60.0)
    confirm_rise_m: float = Field(0.25, gt=0.0, le=2.0)  # further climb that proves a blind rise is stairs
    flight_spread_deg: float = Field(20.0, ge=0.0, le=90.0)  # a confirmed flight vouches this far aside
    profile_bin_m: float = Field(0.1, gt=0.01, le=0.5)
    sensor_range_m: float = Field(5.0, gt=0.0)
    pixel_stride: int = Field(2, ge=1, le=16)
    # Range noise. A depth camera's error spreads a wall's pixels over the range bins in front of it,
    # and the first bin's highest point then reads as the wall: with the noisy robot's depth (sigma =
    # 0.01 * depth^2, 5 % holes) the rays on generated:2 came out 0.1 m short at the median and one in
    # ten more than 0.3 m short, so exploration saw less free space and stopped early. Where the
    # panorama declares its noise (``Panorama.depth_noise_rel``), each pixel takes the median depth of
    # ``noise_median_rows`` rows of its column, but only where the two differ by at most
    # ``noise_gate_sigmas`` of the declared sigma: a wall's pixels share one range and the median pulls
    # the strays back, while an edge larger than the noise (a riser, a table's front) stays as seen.
    # On generated:2 (8 panoramas, 256 px) rays > 0.3 m short went 9.5 % -> 0.8 % (3 rows: 2.2 %; a
    # 2.5-sigma gate: 5 %). Exact depth (declared 0) is not touched: noise-free rays stay bit-identical,
    # and the stairs of tests/unit/mapper/test_stairs.py with them (a plain 3-row median, applied to
    # exact depth too, lost a 64 px camera's second floor). 1: off.
    noise_median_rows: int = Field(5, ge=1, le=9)
    noise_gate_sigmas: float = Field(4.0, gt=0.0, le=10.0)
    smoothing_deg: float = Field(9.0, ge=0.0, le=90.0)
    nms_angle_deg: float = Field(30.0, gt=0.0, le=180.0)
    min_score: float = Field(0.15, ge=0.0, le=1.0)
    distance_sigma_m: float = Field(0.4, gt=0.0)
    # Doorways: an opening between two near edges of the obstacle profile (jambs) that the body cannot
    # pass in a straight line from here gets an *approach* waypoint lined up with it, as a trained CWP
    # puts waypoints in front of doors. Without it an agent beside a wall never sees a way through.
    doorways: bool = True
    door_min_width_m: float = Field(0.6, gt=0.0)  # between the jambs' nearest points
    door_max_width_m: float = Field(1.8, gt=0.0)
    door_depth_m: float = Field(0.5, gt=0.0)  # the opening must reach this far behind the jambs
    door_approach_m: tuple[float, ...] = (0.6, 0.45, 0.8, 0.3)  # stand-off before the door, preferred first
    door_through_m: float = Field(0.6, gt=0.0)  # the straight shot checked from the approach point
    door_score: float = Field(0.9, gt=0.0, le=1.0)  # heatmap value of an approach waypoint
    max_door_candidates: int = Field(2, ge=0, le=32)
    nms_distance_m: float = Field(1.0, gt=0.0)  # a doorway waypoint suppresses only this near in distance
    # Boxed in: where no candidate clears the full clearance (body_radius_m + clearance_margin_m), the
    # free distances are swept again with this smaller disc, so that a robot standing nearer to a wall
    # than its clearance can still get away from it; a panorama that has a candidate is not touched.
    # Obstacles the smaller disc already overlaps block only the directions that approach them (see
    # sweep). It lies below the profile's 0.1 m bin because the profile reads an obstacle at the near
    # edge of its bin: a wall 0.1-0.2 m away reads 0.1 m over an arc of up to 100 deg, and a disc of
    # 0.1 m may not move towards any point of that arc, so it could only back straight off into
    # whatever stands behind. On the 5 of 300 seed-0 ablation episodes that ended at step 0 (ids 126,
    # 174, 233, 255, 258): 0.1 m gives 4 of them a candidate (not 255), 0.075 m all 5, and the
    # simulator walks 12 of their 13 candidates to the end (one stops after 0.19 of 0.5 m). At or above
    # the clearance, or None: off (the exploration's own way out of a dead end is the graph, discovery.py).
    escape_clearance_m: float | None = Field(0.075, ge=0.0, le=1.0)

    @model_validator(mode="after")
    def _ranges(self):
        if self.noise_median_rows % 2 == 0:
            raise ValueError("noise_median_rows must be odd (a pixel and as many rows above as below)")
        if self.max_distance_m <= self.min_distance_m:
            raise ValueError("max_distance_m must exceed min_distance_m")
        if self.sensor_range_m < self.max_distance_m:
            raise ValueError("sensor_range_m must be at least max_distance_m")
        if self.door_max_width_m <= self.door_min_width_m:
            raise ValueError("door_max_width_m must exceed door_min_width_m")
        if not self.door_approach_m or min(self.door_approach_m) <= 0.0:
            raise ValueError("door_approach_m needs at least one positive stand-off")
        return self

    @property
    def clearance_m(self) -> float:
        return self.body_radius_m + self.clearance_margin_m


def _column_median_within_noise(depth: np.ndarray, noise_rel: float, rows: int, gate_sigmas: float) -> np.ndarray:
    """Each pixel's depth replaced by the median of ``rows`` rows of its image column (itself in the
    middle) where the two differ by at most ``gate_sigmas`` * sigma, sigma = ``noise_rel`` * median^2.

    Holes (0) stay holes and do not vote: a pixel beside a hole takes the median of the rows that
    measured, so a hole does not pull its neighbours nearer. Along columns only, so a doorway a few
    columns wide keeps its width. Shared by the compiled and the array column walk, and computed
    the same way by :func:`_column_median_kernel` (same float32 median, float64 gate)."""
    views, height, width = depth.shape
    half = rows // 2
    measured = np.where(depth > 0.0, depth, np.nan)  # 0 and NaN: no measurement
    padded = np.full((views, height + 2 * half, width), np.nan, dtype=depth.dtype)
    padded[:, half:half + height] = measured
    window = np.stack([padded[:, k:k + height] for k in range(rows)])
    ordered = np.sort(window, axis=0)  # NaN sorts last
    n = np.isfinite(window).sum(axis=0)
    lo = np.take_along_axis(ordered, ((n - 1) // 2)[None], axis=0)[0]
    hi = np.take_along_axis(ordered, (n // 2)[None], axis=0)[0]
    median = (lo + hi).astype(depth.dtype) * depth.dtype.type(0.5)
    m64 = median.astype(np.float64)
    gate = (gate_sigmas * noise_rel) * m64 * m64
    close = np.abs(m64 - measured.astype(np.float64)) <= gate  # False where either is a hole
    return np.where(close, median, depth)


def _column_median_kernel(depth, rows, gate_scale, out):  # pragma: no cover - compiled
    """:func:`_column_median_within_noise` pixel by pixel (an insertion sort of the few rows), with
    the same float32 median and the same float64 gate, so the same depth to the bit."""
    views, height, width = depth.shape
    half = rows // 2
    buf = np.empty(rows, dtype=depth.dtype)
    half_f = np.float32(0.5)  # float32 depth: a float32 median, as numpy's
    for v in range(views):
        for c in range(width):
            for r in range(height):
                d = depth[v, r, c]
                out[v, r, c] = d
                if not d > 0.0:
                    continue
                n = np.int64(0)  # not the literal 0, for which numba would compile insert_sorted again
                for k in range(max(r - half, 0), min(r + half + 1, height)):
                    x = depth[v, k, c]
                    if not x > 0.0:
                        continue
                    n = insert_sorted(buf, n, x)
                med = (buf[(n - 1) // 2] + buf[n // 2]) * half_f
                m64 = np.float64(med)
                if abs(m64 - np.float64(d)) <= gate_scale * m64 * m64:
                    out[v, r, c] = med


class _Memo:
    """The last panorama's column walk: (panorama, hits), replaced as one tuple (thread-safe reads)."""

    last: tuple[Panorama, _ColumnHits] | None = None


@dataclass(frozen=True)
class _ColumnHits:
    """Per image column (views x columns, flattened): the first obstacle's range, the range where an
    unconfirmed climb was first seen, whether a blind-zone climb was confirmed (a flight), azimuth."""

    hit: np.ndarray
    doubt: np.ndarray
    climbed: np.ndarray
    azimuth_rad: np.ndarray


@dataclass
class _ColumnWalk:
    """State of the outward walk along every image column, one entry per column.

    The ground may rise by less than a step per profile bin (stairs, ramps); the first bin whose
    highest point rises more than that is the obstacle. Points above the body band were dropped, so
    ceilings and lamps never block. The camera cannot see the floor right in front of the feet (and
    far rows are sparse), so the first surface after a blind stretch may already be a few treads up
    a staircase - or the top of a bed whose front edge hides in the blind zone. Such a rise is
    accepted only tentatively: it must be *confirmed* by the ground climbing on by
    ``confirm_rise_m`` (more treads); a surface that stays flat, drops away or ends at a wall was
    furniture.
    """

    ground: np.ndarray  # height of the walkable ground reached so far
    hit: np.ndarray  # range of the first obstacle (inf: none yet)
    open_: np.ndarray  # still walking
    last_r: np.ndarray  # range of the last surface seen (the feet at first)
    tentative: np.ndarray  # where an unconfirmed climb's obstacle would stand
    tent_z: np.ndarray
    tent_first: np.ndarray  # where that raised surface was first seen
    strict: np.ndarray  # the pending climb's edge hid in the blind zone
    climbed: np.ndarray  # a blind-zone climb was confirmed: a flight
    doubt: np.ndarray  # unconfirmed climb: where it was first seen

    @classmethod
    def start(cls, n: int) -> _ColumnWalk:
        inf = lambda: np.full(n, np.inf)  # noqa: E731
        return cls(ground=np.zeros(n), hit=inf(), open_=np.ones(n, dtype=bool), last_r=np.zeros(n),
                   tentative=inf(), tent_z=np.zeros(n), tent_first=inf(), strict=np.zeros(n, dtype=bool),
                   climbed=np.zeros(n, dtype=bool), doubt=inf())

    def run(self, top: np.ndarray, vertical: np.ndarray, c: GeometricPredictorConfig, low_tan: float) -> None:
        tan_slope = math.tan(math.radians(c.max_slope_deg))
        near_edge_m = c.clearance_m + c.profile_bin_m
        for b in range(top.shape[1]):
            self._bin(b, top[:, b], vertical[:, b], c, tan_slope, low_tan, near_edge_m)
        # A climb out of the blind zone never confirmed by the end of what the column saw was
        # furniture, not stairs. (Far climbs after a sparse-row gap are judged by the drop alone:
        # above the camera only risers are visible, so a flight's top never looks confirmed.)
        left = self.open_ & np.isfinite(self.tentative) & self.strict
        self.hit[left] = self.tentative[left]
        self.doubt[left] = self.tent_first[left]

    def _bin(self, b: int, t: np.ndarray, vertical: np.ndarray, c: GeometricPredictorConfig,
             tan_slope: float, low_tan: float, near_edge_m: float) -> None:
        seen = np.isfinite(t) & self.open_
        if not seen.any():
            return
        r_b = b * c.profile_bin_m  # near edge of the bin: conservative
        rise = t - self.ground
        # Over a stretch nobody saw (pixel rows are sparse far away), the ground may have
        # climbed as much as the steepest walkable slope allows.
        slope_ok = rise <= c.max_step_m + tan_slope * np.maximum(r_b - self.last_r - c.profile_bin_m, 0.0)
        pending = np.isfinite(self.tentative)
        confirmed = seen & pending & (t >= self.tent_z + c.confirm_rise_m) & (rise <= c.max_step_m)
        self.tentative[confirmed] = np.inf
        self.climbed |= confirmed & self.strict
        self.strict[confirmed] = False
        pending &= ~confirmed
        blocked = seen & (rise > c.max_step_m) & (~slope_ok | vertical)
        dropped = seen & (rise < -c.max_step_m) & pending
        unconfirmed = blocked & pending & self.strict
        self.hit[blocked] = np.where(unconfirmed[blocked], self.tentative[blocked], r_b)
        self.doubt[unconfirmed] = self.tent_first[unconfirmed]
        # A surface that drops away again is a step-up/step-down block; its far edge decides
        # nothing, and a flight seen from its side drops too: stop where it was first seen.
        self.hit[dropped] = self.tent_first[dropped]
        self.open_ &= ~(blocked | dropped)
        new_tent = seen & self.open_ & slope_ok & (rise > c.max_step_m) & ~pending
        if new_tent.any():
            # Where did the raised surface begin? Seen well past the range from which the lowest
            # ray would have caught it, it begins where it was first seen; otherwise its edge
            # hides in the blind stretch, assumed just beyond the body.
            visible_from = (c.camera_height_m - t) / low_tan
            hidden = r_b <= visible_from + 2.0 * c.profile_bin_m
            edge = np.where(hidden, np.maximum(self.last_r, np.minimum(r_b, near_edge_m)), r_b)
            self.tentative[new_tent] = edge[new_tent]
            self.tent_z[new_tent] = t[new_tent]
            self.tent_first[new_tent] = r_b
            self.strict[new_tent] = hidden[new_tent]
        walk = seen & self.open_ & (rise > -4.0 * c.max_step_m)
        self.ground[walk] = t[walk]
        self.last_r[seen] = r_b


def _column_walk_kernel(top, vertical, max_step, tan_slope, bin_m, confirm_rise, cam_h, low_tan, near_edge_m,
                        hit, doubt, climbed):  # pragma: no cover - compiled
    """:class:`_ColumnWalk` one column at a time, each column's state in scalars: the same comparisons
    and the same floating-point operations in the same order, so the same hits to the bit. The array
    version runs every bin for all columns at once; a column's state depends only on its own bins."""
    two_bins = 2.0 * bin_m
    low_ground = -4.0 * max_step
    for i in range(top.shape[0]):
        ground = 0.0
        col_hit = np.inf
        col_doubt = np.inf
        last_r = 0.0
        tentative = np.inf
        tent_z = 0.0
        tent_first = np.inf
        strict = False
        col_climbed = False
        for b in range(top.shape[1]):
            t = top[i, b]
            if not np.isfinite(t):
                continue
            r_b = b * bin_m
            rise = t - ground
            slope_ok = rise <= max_step + tan_slope * max(r_b - last_r - bin_m, 0.0)
            pending = np.isfinite(tentative)
            if pending and t >= tent_z + confirm_rise and rise <= max_step:  # a blind-zone climb confirmed
                tentative = np.inf
                col_climbed |= strict
                strict = False
                pending = False
            if rise > max_step and (not slope_ok or vertical[i, b]):
                if pending and strict:
                    col_hit = tentative
                    col_doubt = tent_first
                else:
                    col_hit = r_b
                break
            if rise < -max_step and pending:
                col_hit = tent_first
                break
            if slope_ok and rise > max_step and not pending:
                visible_from = (cam_h - t) / low_tan
                if r_b <= visible_from + two_bins:
                    tentative = max(last_r, min(r_b, near_edge_m))
                    strict = True
                else:
                    tentative = r_b
                    strict = False
                tent_z = t
                tent_first = r_b
            if rise > low_ground:
                ground = t
            last_r = r_b
        else:
            if np.isfinite(tentative) and strict:
                col_hit = tentative
                col_doubt = tent_first
        hit[i] = col_hit
        doubt[i] = col_doubt
        climbed[i] = col_climbed


def _profiles_kernel(depth, range_scale, yn, cam_h, bin_m, nb, band_top_m, max_vertical_m, top, vertical):  # pragma: no cover - compiled
    """:meth:`GeometricPredictor._profiles` in one pass over the pixels (no index arrays, no
    ``ufunc.at``), with the same per-pixel arithmetic."""
    views, rows, cols = depth.shape
    bottom = np.full(top.shape, np.inf)
    for v in range(views):
        for r in range(rows):
            for c in range(cols):
                d = depth[v, r, c]
                if not (np.isfinite(d) and d > 0.0):
                    continue
                rng = d * range_scale[c]
                k = np.floor(rng / bin_m)
                height = cam_h - yn[r] * d
                if not (k < nb and height < band_top_m):
                    continue
                col = v * cols + c
                kb = np.int64(k)
                if height > top[col, kb]:
                    top[col, kb] = height
                if height < bottom[col, kb]:
                    bottom[col, kb] = height
    for col in range(top.shape[0]):
        for kb in range(top.shape[1]):
            vertical[col, kb] = (top[col, kb] - bottom[col, kb]) > max_vertical_m


if AVAILABLE:
    # Compiled on first use (and kept in numba's disk cache): importing the module stays cheap.
    _column_walk_kernel = kernel(error_model="numpy")(_column_walk_kernel)
    # One signature each for every depth they are given (shared.jit.one_signature): the strided view of
    # the configured pixel stride, a stride of 1's contiguous array, a panorama's read-only depth; numba
    # compiled _profiles_kernel three times and _column_median_kernel twice for these (0.3-0.7 s of CPU
    # each on a cold cache), the same arithmetic every time.
    _profiles_kernel = one_signature(kernel(error_model="numpy")(_profiles_kernel),
                                     read_only=(0, 1, 2))
    _column_median_kernel = one_signature(
        kernel(error_model="numpy")(_column_median_kernel), read_only=(0,))

_warm = False


def _warm_up(stride: int) -> None:
    """Compile (or load from the disk cache) the kernels now, when a predictor is built, so that the
    first panorama does not pay for it. One signature serves every stride (above)."""
    global _warm
    if not AVAILABLE or _warm:
        return
    depth = np.ones((1, 2 * stride, 2 * stride), np.float32)[:, ::stride, ::stride]
    top, vertical = np.full((2, 1), -np.inf), np.zeros((2, 1), dtype=bool)
    _profiles_kernel(depth, np.ones(2), np.ones(2), 1.0, 0.1, 1, 1.0, 0.3, top, vertical)
    _column_median_kernel(depth, 3, 0.04, np.empty(depth.shape, np.float32))
    _column_walk_kernel(top, vertical, 0.2, 0.5, 0.1, 0.25, 1.0, 1.0, 0.3, np.empty(2), np.empty(2),
                        np.empty(2, dtype=bool))
    _warm = True


@PREDICTORS.register("geometric", GeometricPredictorConfig)
class GeometricPredictor:
    """CWP-contract predictor computed from depth geometry alone (no learning, a few ms)."""

    #: The per-panorama column walk as compiled loops when numba is installed; False runs the array
    #: version (:class:`_ColumnWalk`), which gives the same hits and is what the tests compare against.
    use_kernel: bool = True

    def __init__(self, config: GeometricPredictorConfig | None = None):
        self.config = config or GeometricPredictorConfig()
        c = self.config
        self.angles_rad = np.arange(c.angle_bins) * (2.0 * math.pi / c.angle_bins)
        self.angles_rad = wrap_angle(self.angles_rad)
        self.distances_m = np.linspace(c.min_distance_m, c.max_distance_m, c.distance_bins)
        self._profile_edges = np.arange(0.0, c.sensor_range_m + c.profile_bin_m, c.profile_bin_m)
        # Pairwise angular offsets between travel directions and obstacle bins, for the body sweep.
        d = wrap_angle(self.angles_rad[:, None] - self.angles_rad[None, :])
        self._cos = np.cos(d)
        self._sin = np.abs(np.sin(d))
        self._column_cache: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._memo = _Memo()
        if self.use_kernel:
            _warm_up(c.pixel_stride)

    # --- public ---------------------------------------------------------------------------------

    def predict(self, panorama: Panorama) -> list[Candidate]:
        return self.predict_full(panorama).candidates

    def predict_full(self, panorama: Panorama) -> Prediction:
        """Candidates plus the heatmap and free-space profile they came from.

        Swept at the full body clearance; only where that leaves no candidate at all (the robot is
        boxed in) again at ``escape_clearance_m`` (see the config)."""
        c = self.config
        obst = self.obstacle_distance(panorama)
        prediction = self._predict_at(obst, c.clearance_m, panorama.pose.heading_rad)
        if prediction.candidates or c.escape_clearance_m is None or c.escape_clearance_m >= c.clearance_m:
            return prediction
        return self._predict_at(obst, c.escape_clearance_m, panorama.pose.heading_rad)

    def _predict_at(self, obst: np.ndarray, clearance_m: float, heading_rad: float) -> Prediction:
        free = self._free_from_obstacles(obst, clearance_m)
        heatmap = self.heatmap(free)
        # A doorway's approach point must be reachable at this clearance; the straight shot through
        # the door from there keeps the full one (by then the robot is out of the box).
        doors = self.doorways(obst, free) if self.config.doorways else []
        priority = self._door_peaks(heatmap, doors)
        candidates = self._nms(heatmap, heading_rad, priority)
        return Prediction(candidates, heatmap, doors, free, self.angles_rad, self.distances_m, clearance_m)

    def obstacle_distance(self, panorama: Panorama) -> np.ndarray:
        """Horizontal distance to the nearest obstacle per angle bin (``inf``: none in range)."""
        cols = self._column_hits(panorama)
        return self._bin_columns(cols)

    def with_angle_bins(self, angle_bins: int) -> GeometricPredictor:
        """The same predictor at another angular resolution, sharing the per-panorama column walk
        (the explorer's 360-ray scan and the 120-bin prediction then cost one walk, not two)."""
        other = GeometricPredictor(self.config.model_copy(update={"angle_bins": angle_bins}))
        other._memo = self._memo
        return other

    def _column_hits(self, panorama: Panorama) -> _ColumnHits:
        last = self._memo.last
        if last is not None and last[0] is panorama:
            return last[1]
        hits = self._walk_columns(panorama)
        self._memo.last = (panorama, hits)
        return hits

    def _walk_columns(self, panorama: Panorama) -> _ColumnHits:
        """Where each image column meets its first obstacle, walking outward over the ground."""
        c = self.config
        depth = np.asarray(panorama.depth_m)
        if depth.ndim != 3:
            raise PredictorError(f"panorama depth must be (V, H, W), got {depth.shape}")
        s = c.pixel_stride
        depth = depth[:, ::s, ::s]
        if panorama.depth_noise_rel > 0.0 and c.noise_median_rows > 1:
            if self.use_kernel and AVAILABLE:
                smoothed = np.empty(depth.shape, dtype=depth.dtype)
                _column_median_kernel(depth, c.noise_median_rows, c.noise_gate_sigmas * panorama.depth_noise_rel,
                                      smoothed)
                depth = smoothed
            else:
                depth = _column_median_within_noise(depth, panorama.depth_noise_rel, c.noise_median_rows,
                                                    c.noise_gate_sigmas)
        cam = panorama.camera
        xn, yn, col_angle = self._columns(cam.width_px, cam.height_px, cam.hfov_deg, s)
        views, rows, cols = depth.shape
        top, vertical = self._profiles(depth, xn, yn)
        # Lowest sampled ray: a surface of height t is visible from range (cam_h - t) / low_tan on.
        low_tan = max(float(yn.max()), 1e-3)
        if self.use_kernel and AVAILABLE:
            n = views * cols
            hit, doubt, climbed = np.empty(n), np.empty(n), np.empty(n, dtype=bool)
            _column_walk_kernel(top, vertical, c.max_step_m, math.tan(math.radians(c.max_slope_deg)), c.profile_bin_m,
                                c.confirm_rise_m, c.camera_height_m, low_tan, c.clearance_m + c.profile_bin_m,
                                hit, doubt, climbed)
        else:
            walk = _ColumnWalk.start(views * cols)
            walk.run(top, vertical, c, low_tan=low_tan)
            hit, doubt, climbed = walk.hit, walk.doubt, walk.climbed
        # Column azimuth relative to the agent heading; views look at headings_rad[i].
        heads = np.asarray(panorama.headings_rad, dtype=np.float64) - panorama.pose.heading_rad
        az = wrap_angle(heads[:, None] - col_angle[None, :]).ravel()
        return _ColumnHits(hit, doubt, climbed, az)

    def _profiles(self, depth: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per image column and range bin: the highest surface point, and whether the bin is a
        vertical face (its points span more height than a step plus the steepest slope)."""
        c = self.config
        views, rows, cols = depth.shape
        nb = len(self._profile_edges) - 1
        max_vertical_m = c.max_step_m + math.tan(math.radians(c.max_slope_deg)) * c.profile_bin_m
        if self.use_kernel and AVAILABLE:
            top = np.full((views * cols, nb), -np.inf)
            vertical = np.empty((views * cols, nb), dtype=bool)
            _profiles_kernel(depth, np.sqrt(1.0 + xn * xn), yn, c.camera_height_m, c.profile_bin_m, nb,
                             c.body_height_m + c.max_step_m, max_vertical_m, top, vertical)
            return top, vertical
        valid = np.isfinite(depth) & (depth > 0.0)
        rng = np.where(valid, depth * np.sqrt(1.0 + xn * xn)[None, None, :], np.inf)
        height = c.camera_height_m - yn[None, :, None] * depth  # above the agent's floor
        rbin = np.floor(rng / c.profile_bin_m)
        inband = valid & (rbin < nb) & (height < c.body_height_m + c.max_step_m)
        col_id = (np.arange(views)[:, None, None] * cols + np.arange(cols)[None, None, :])
        col_id = np.broadcast_to(col_id, depth.shape)
        flat = (col_id[inband] * nb + rbin[inband].astype(np.int64))
        top = np.full(views * cols * nb, -np.inf)
        np.maximum.at(top, flat, height[inband])
        top = top.reshape(views * cols, nb)
        bottom = np.full(views * cols * nb, np.inf)
        np.minimum.at(bottom, flat, height[inband])
        # A wall or a sofa front is never walkable, whatever blind stretch came before it.
        vertical = (top - bottom.reshape(views * cols, nb)) > max_vertical_m
        return top, vertical

    def _bin_columns(self, cols: _ColumnHits) -> np.ndarray:
        c = self.config
        step = 2.0 * math.pi / c.angle_bins
        abin = np.round(cols.azimuth_rad / step).astype(np.int64) % c.angle_bins
        hit = cols.hit
        # An unconfirmed climb beside a confirmed flight is the same flight seen at a slant (its
        # side wall ends the column early): trust where it was first seen, not the blind edge.
        flight = np.zeros(c.angle_bins, dtype=bool)
        flight[abin[cols.climbed]] = True
        if flight.any():
            half = max(1, int(round(c.flight_spread_deg / (360.0 / c.angle_bins))))
            near = np.zeros_like(flight)
            for k in range(-half, half + 1):
                near |= np.roll(flight, k)
            relax = near[abin] & np.isfinite(cols.doubt)
            hit = np.where(relax, cols.doubt, hit)
        out = np.full(c.angle_bins, np.inf)
        np.minimum.at(out, abin, hit)
        covered = np.zeros(c.angle_bins, dtype=bool)
        covered[abin] = True
        # A direction no pixel looked at is unknown, not free: NaN lets free_distance close it.
        out[~covered] = np.nan
        return out

    def free_distance(self, panorama: Panorama) -> np.ndarray:
        """How far the agent's body (radius + margin) can travel along each angle bin."""
        return self._free_from_obstacles(self.obstacle_distance(panorama), self.config.clearance_m)

    def _free_from_obstacles(self, obst: np.ndarray, clearance_m: float) -> np.ndarray:
        unseen = np.isnan(obst)
        free = self.sweep(np.where(unseen, np.inf, obst), clearance_m, self.config.sensor_range_m)
        free[unseen] = 0.0
        return free

    def doorways(self, obstacle_m: np.ndarray, free_m: np.ndarray) -> list[Doorway]:
        """Openings between two near profile edges, each with a reachable approach point if any.

        A doorway is a run of angle bins whose obstacles lie at least ``door_depth_m`` behind both
        flanking bins (the jambs), the jambs ``door_min_width_m``..``door_max_width_m`` apart. Its
        approach point stands ``door_approach_m`` before the opening's centre on its normal; it must be
        reachable in a straight line (``free_m``) and the straight shot from it through the opening
        must clear every obstacle point of the profile by the body clearance.
        """
        c = self.config
        n = len(obstacle_m)
        r = np.where(np.isnan(obstacle_m), 0.0, obstacle_m)  # unseen: treat as a near wall, never a gap
        far = np.where(np.isfinite(r), r, c.sensor_range_m + c.door_depth_m)
        pts = np.stack([np.cos(self.angles_rad), np.sin(self.angles_rad)], axis=1) * np.where(
            np.isfinite(r), r, np.nan)[:, None]
        known = np.isfinite(pts[:, 0]) & (r > 0.0)
        # Rising edges: bin i near, bin i+1 far behind it. The run then ends at the first bin j that
        # is near again; spans are short (a door seen from 0.3 m spans < 180 deg), so loop the edges.
        nxt = np.roll(far, -1)
        rising = np.flatnonzero(known & (nxt > far + c.door_depth_m))
        max_span = n // 2
        out: list[Doorway] = []
        # The scan below reads single elements: Python lists hold the same float64 values and read
        # ten times faster than numpy scalars (a few hundred reads per panorama).
        far_l, known_l, open_l = far.tolist(), known.tolist(), np.isinf(r).tolist()
        for i in rising.tolist():
            ri = far_l[i]
            j = -1
            run_min = far_l[(i + 1) % n]
            for step in range(2, max_span):
                k = (i + step) % n
                if not known_l[k] and not open_l[k]:
                    break  # an unseen direction: the run's far side is unknown
                if known_l[k] and far_l[k] + c.door_depth_m <= run_min:
                    j = k  # falling edge: the other jamb
                    break
                run_min = min(run_min, far_l[k])
            if j < 0:
                continue
            inner = (i + 1 + np.arange(step - 1)) % n
            if np.any(far[inner] < max(ri, far_l[j]) + c.door_depth_m):
                continue
            p_right, p_left = pts[i], pts[j]  # angles grow to the left
            width = float(np.linalg.norm(p_left - p_right))
            if not (c.door_min_width_m <= width <= c.door_max_width_m):
                continue
            # Obstacles the straight shot must clear: everything seen except what lies beyond the opening.
            others = known.copy()
            others[inner] = False
            out.append(self._door(p_left, p_right, width, free_m, pts[others]))
        return out

    def _door(self, p_left: np.ndarray, p_right: np.ndarray, width: float, free_m: np.ndarray,
              obstacles: np.ndarray) -> Doorway:
        c = self.config
        mid = 0.5 * (p_left + p_right)
        t = (p_left - p_right) / width
        normal = np.array([t[1], -t[0]])
        if normal @ mid < 0.0:
            normal = -normal
        through = mid + c.door_through_m * normal
        # Already passable straight from here: the regular heatmap offers it.
        direct = self._reachable(through, free_m)
        approach = None
        if not direct:
            for stand_off in c.door_approach_m:
                a = mid - stand_off * normal
                dist = float(np.hypot(*a))
                if dist < c.min_distance_m or dist > c.max_distance_m:
                    continue
                if self._reachable(a, free_m) and self._segment_clear(a, through, obstacles):
                    approach = a
                    break
        return Doorway(tuple(map(float, p_left)), tuple(map(float, p_right)), width,
                       None if approach is None else (float(approach[0]), float(approach[1])), direct)

    def _reachable(self, point: np.ndarray, free_m: np.ndarray) -> bool:
        step = 2.0 * math.pi / self.config.angle_bins
        k = int(round(math.atan2(point[1], point[0]) / step)) % self.config.angle_bins
        return bool(free_m[k] + 1e-9 >= math.hypot(point[0], point[1]))

    def _segment_clear(self, a: np.ndarray, b: np.ndarray, points: np.ndarray) -> bool:
        """Does a disc of the body clearance pass from ``a`` to ``b`` without touching ``points``?"""
        ab = b - a
        t = np.clip(((points - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        d = np.linalg.norm(points - (a + t[:, None] * ab), axis=1)
        return bool(np.all(d >= self.config.clearance_m))

    def _door_peaks(self, heatmap: np.ndarray, doors: list[Doorway]) -> list[tuple[int, int]]:
        """Write the doorway approach points into the heatmap; their bins, nearest door first."""
        c = self.config
        step = 2.0 * math.pi / c.angle_bins
        peaks: list[tuple[float, int, int]] = []
        for d in doors:
            if d.approach_m is None:
                continue
            ax, ay = d.approach_m
            ai = int(round(math.atan2(ay, ax) / step)) % c.angle_bins
            di = int(np.argmin(np.abs(self.distances_m - math.hypot(ax, ay))))
            heatmap[ai, di] = max(heatmap[ai, di], c.door_score)
            peaks.append((float(np.hypot(*np.add(d.left_m, d.right_m))), ai, di))
        peaks.sort()
        return [(ai, di) for _, ai, di in peaks[: c.max_door_candidates]]

    def sweep(self, obstacle_m: np.ndarray, radius_m: float, cap_m: float) -> np.ndarray:
        """Travel distance of a disc of ``radius_m`` per direction before touching an obstacle."""
        finite = np.isfinite(obstacle_m)[None, :]
        d = np.where(finite, obstacle_m[None, :], 0.0)
        lateral = d * self._sin
        along = d * self._cos
        # Only obstacles ahead matter: moving away from a point never brings the disc closer, even
        # when the robot already stands nearer to it than the radius (the body sizes differ).
        touches = finite & (lateral < radius_m) & (along > 0.0)
        stop = along - np.sqrt(np.maximum(radius_m**2 - lateral**2, 0.0))
        stop = np.where(touches, stop, np.inf)
        free = np.min(stop, axis=1)
        return np.clip(free, 0.0, cap_m)

    def heatmap(self, free_m: np.ndarray) -> np.ndarray:
        """Angle x distance scores in [0, 1]; zero wherever the body would not fit."""
        c = self.config
        # Openness of a direction: its free distance, smoothed over neighbouring angles so that
        # a single noisy column does not open a corridor and doorways stand out as peaks.
        open_frac = np.clip(free_m / c.max_distance_m, 0.0, 1.0)
        if c.smoothing_deg > 0:
            half = max(1, int(round(c.smoothing_deg / (360.0 / c.angle_bins))))
            kernel = np.hanning(2 * half + 3)[1:-1]
            kernel /= kernel.sum()
            padded = np.concatenate([open_frac[-half:], open_frac, open_frac[:half]])
            smooth = np.convolve(padded, kernel, mode="valid")
            # A direction is never more open than its own free distance allows.
            open_frac = np.minimum(smooth, open_frac)
        target = np.clip(free_m, c.min_distance_m, c.max_distance_m)
        dist = self.distances_m[None, :]
        reach = dist <= free_m[:, None] + 1e-9
        pref = np.exp(-0.5 * ((dist - target[:, None]) / c.distance_sigma_m) ** 2)
        return np.where(reach, open_frac[:, None] * pref, 0.0)

    # --- internals ------------------------------------------------------------------------------

    def _columns(self, width: int, height: int, hfov_deg: float, stride: int):
        key = (width, height, hfov_deg, stride)
        if key not in self._column_cache:
            f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
            u = np.arange(0, width, stride, dtype=np.float64)
            v = np.arange(0, height, stride, dtype=np.float64)
            xn = (u - (width - 1) / 2.0) / f
            yn = (v - (height - 1) / 2.0) / f
            # Camera x points right, so a column right of centre looks clockwise of the view.
            self._column_cache[key] = (xn, yn, np.arctan(xn))
        return self._column_cache[key]

    def _nms(self, heatmap: np.ndarray, heading_rad: float,
             priority: list[tuple[int, int]] | None = None) -> list[Candidate]:
        c = self.config
        h = heatmap.copy()
        na = c.angle_bins
        half = int(round(c.nms_angle_deg / (360.0 / na)))
        out: list[Candidate] = []
        # Doorway approaches first: they suppress only nearby distances of nearby angles, so the long
        # move past the door in the same direction survives.
        near_d = np.abs(self.distances_m[:, None] - self.distances_m[None, :]) <= c.nms_distance_m + 1e-9
        for ai, di in priority or []:
            if len(out) >= c.max_candidates or h[ai, di] < c.min_score:
                continue
            out.append(self._candidate(len(out), ai, di, float(h[ai, di]), heading_rad))
            rows = (np.arange(ai - half, ai + half + 1)) % na
            h[np.ix_(rows, np.flatnonzero(near_d[di]))] = 0.0
        while len(out) < c.max_candidates:
            k = int(np.argmax(h))
            ai, di = divmod(k, h.shape[1])
            score = float(h[ai, di])
            if score < c.min_score or score <= 0.0:
                break
            out.append(self._candidate(len(out), ai, di, score, heading_rad))
            rows = (np.arange(ai - half, ai + half + 1)) % na
            h[rows, :] = 0.0
        return out

    def _candidate(self, index: int, ai: int, di: int, score: float, heading_rad: float) -> Candidate:
        angle = float(self.angles_rad[ai])
        dist = float(self.distances_m[di])
        world = heading_rad + angle
        return Candidate(index=index, kind=CandidateKind.WAYPOINT, dx_m=dist * math.cos(world),
                         dy_m=dist * math.sin(world), angle_rad=angle, distance_m=dist, score=score)


def create_predictor(name: str = DEFAULT_PREDICTOR, config=None) -> WaypointPredictor:
    """The named predictor backend (``geometric`` unless told otherwise)."""
    return PREDICTORS.create(name, config)
