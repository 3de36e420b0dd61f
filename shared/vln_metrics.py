"""VLN-CE metrics, exactly as the community computes them.

Definitions follow VLN-CE (``habitat_extensions/measures.py``) and habitat-lab
(``DistanceToGoal``, ``Success``, ``SPL``), with DTW from Magalhaes et al. 2019 (R4R ``dtw.py``):

* **NE**  - geodesic distance from the final position to the goal.
* **SR**  - success: the agent called stop *and* ``NE < success_distance_m`` (strict, as habitat).
* **OSR** - oracle success: some position of the trajectory had a geodesic distance ``< success_distance_m``.
* **TL**  - trajectory length: the sum of the Euclidean lengths of the steps between positions.
* **SPL** - ``S * L / max(L, TL)`` with ``L`` the geodesic start-goal distance.
* **nDTW** - ``exp(-DTW(P, R) / (|R| * success_distance_m))``; DTW over Euclidean point distances, exact by
  default (VLN-CE's ``dtw`` package) or ``fastdtw`` (VLN-CE's ``FDTW: True`` default) when installed.
  As VLN-CE does, consecutive duplicate positions of the agent path are dropped before DTW.
* **SDTW** - ``SR * nDTW``.

Geodesic distances come from a callable the caller supplies (the simulator's nav grid). A Euclidean
stand-in exists (:func:`euclidean_geodesic`) but is never used unless the caller passes it explicitly:
a metric computed through walls is not a VLN-CE metric. An unreachable goal (no path, ``None`` or
``inf`` from the callable) is reported as such (``ne_m=None``, ``goal_reachable=False``), never as NaN.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

SUCCESS_DISTANCE_M = 3.0

GeodesicFn = Callable[[np.ndarray, np.ndarray], "float | None"]
"""``geodesic(a_m, b_m) -> metres``; ``None`` or ``inf`` when ``b`` cannot be reached from ``a``."""

PointDistanceFn = Callable[[np.ndarray, np.ndarray], float]


class MetricsError(ValueError):
    """Invalid input to a metric (empty paths, wrong shapes, non-finite coordinates)."""


def euclidean_geodesic(a_m, b_m) -> float:
    """Straight-line stand-in for a geodesic; only for callers that explicitly accept the error."""
    return float(np.linalg.norm(np.asarray(b_m, dtype=np.float64) - np.asarray(a_m, dtype=np.float64)))


def _as_path(points, what: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.size > 0:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[0] == 0:
        raise MetricsError(f"{what} must be a non-empty (N, D) array of positions, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MetricsError(f"{what} contains non-finite coordinates")
    return arr


def _geodesic_or_inf(geodesic: GeodesicFn, a: np.ndarray, b: np.ndarray) -> float:
    d = geodesic(a, b)
    if d is None:
        return math.inf
    d = float(d)
    if math.isnan(d):
        raise MetricsError("the geodesic callable returned NaN; return None or inf for 'unreachable'")
    if d < 0:
        raise MetricsError(f"the geodesic callable returned a negative distance {d}")
    return d


def dedupe_consecutive(path_m) -> np.ndarray:
    """Drop positions equal to their predecessor (VLN-CE records a position only when the agent moved)."""
    p = _as_path(path_m, "path")
    if len(p) == 1:
        return p
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.any(p[1:] != p[:-1], axis=1)
    return p[keep]


def trajectory_length(path_m) -> float:
    """TL: sum of the Euclidean distances between consecutive positions."""
    p = _as_path(path_m, "trajectory")
    if len(p) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def _dtw_from_cost(cost: np.ndarray) -> float:
    """Exact DTW (steps (1,0), (0,1), (1,1), no window) over a pairwise cost matrix.

    The recurrence D[i,j] = c[i,j] + min(D[i-1,j], D[i,j-1], D[i-1,j-1]) is evaluated one anti-diagonal
    at a time: every cell of a diagonal depends only on the two previous diagonals, so each diagonal is
    one vectorised numpy operation (n + m iterations instead of n * m).
    """
    n, m = cost.shape
    acc = np.full((n + 1, m + 1), np.inf)
    acc[0, 0] = 0.0
    for k in range(2, n + m + 1):  # k = i + j over the 1-based indices
        i = np.arange(max(1, k - m), min(n, k - 1) + 1)
        j = k - i
        best = np.minimum(np.minimum(acc[i - 1, j], acc[i, j - 1]), acc[i - 1, j - 1])
        acc[i, j] = cost[i - 1, j - 1] + best
    return float(acc[n, m])


def dtw_distance(
    prediction,
    reference,
    *,
    distance: PointDistanceFn | None = None,
    method: Literal["exact", "fast"] = "exact",
    fast_radius: int = 1,
) -> float:
    """DTW between two paths (lists of points, or of hashable nodes when ``distance`` is given).

    ``distance(a, b)`` defaults to the Euclidean distance between coordinates (VLN-CE). ``method="fast"``
    uses the ``fastdtw`` package (an approximation, VLN-CE's default) and raises if it is not installed.
    """
    if method == "fast":
        try:
            from fastdtw import fastdtw
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise MetricsError("method='fast' needs the 'fastdtw' package (pip install fastdtw)") from exc
        dist = distance or euclidean_geodesic
        return float(fastdtw(list(prediction), list(reference), radius=fast_radius, dist=dist)[0])
    if method != "exact":
        raise MetricsError(f"unknown DTW method {method!r}")
    if distance is None:
        p = _as_path(prediction, "prediction")
        r = _as_path(reference, "reference")
        if p.shape[1] != r.shape[1]:
            raise MetricsError(f"dimension mismatch: prediction {p.shape}, reference {r.shape}")
        cost = np.linalg.norm(p[:, None, :] - r[None, :, :], axis=-1)
    else:
        pred, ref = list(prediction), list(reference)
        if not pred or not ref:
            raise MetricsError("DTW needs non-empty paths")
        cost = np.array([[float(distance(a, b)) for b in ref] for a in pred], dtype=np.float64)
    return _dtw_from_cost(cost)


def ndtw(
    prediction,
    reference,
    *,
    success_distance_m: float = SUCCESS_DISTANCE_M,
    distance: PointDistanceFn | None = None,
    method: Literal["exact", "fast"] = "exact",
) -> float:
    """nDTW = exp(-DTW(P, R) / (|R| * d_th))."""
    n_ref = len(reference)
    if n_ref == 0:
        raise MetricsError("nDTW needs a non-empty reference path")
    d = dtw_distance(prediction, reference, distance=distance, method=method)
    return float(math.exp(-d / (n_ref * success_distance_m)))


def spl(success: bool, shortest_m: float, path_length_m: float) -> float:
    """SPL of one episode: S * L / max(L, PL) (Anderson et al. 2018).

    ``L == PL == 0`` (start on the goal, never moved) counts as a perfect path rather than 0/0. An infinite
    ``L`` (unreachable goal) cannot be a success, so it gives 0.
    """
    if not success or not math.isfinite(shortest_m):
        return 0.0
    denom = max(shortest_m, path_length_m)
    return 1.0 if denom <= 0.0 else float(shortest_m / denom)


@dataclass(frozen=True)
class EpisodeMetrics:
    """The VLN-CE metrics of one episode (fractions in [0, 1], distances in metres)."""

    ne_m: float | None  # None: the goal is unreachable from the final position
    success: bool
    oracle_success: bool
    oracle_ne_m: float | None
    tl_m: float
    spl: float
    ndtw: float | None  # None: no reference path was given
    sdtw: float | None
    shortest_m: float | None  # geodesic start-goal distance L; None: unreachable
    stop_called: bool
    steps: int
    goal_reachable: bool

    def to_dict(self) -> dict:
        return asdict(self)


def episode_metrics(
    trajectory_m,
    goal_m,
    *,
    geodesic: GeodesicFn,
    stop_called: bool,
    reference_path_m=None,
    shortest_m: float | None = None,
    success_distance_m: float = SUCCESS_DISTANCE_M,
    dtw_method: Literal["exact", "fast"] = "exact",
    distances_to_goal_m: Sequence[float | None] | None = None,
) -> EpisodeMetrics:
    """Compute every VLN-CE metric of one episode.

    Args:
        trajectory_m: (T, 3) agent positions, the start first. Pass the densest positions you have (VLN-CE
            records one per 0.25 m action); TL and nDTW are only comparable at a similar density.
        goal_m: (3,) goal position.
        geodesic: ``geodesic(a, b)`` in metres, ``None``/``inf`` when unreachable. Pass
            :func:`euclidean_geodesic` explicitly to accept straight-line distances.
        stop_called: whether the agent called stop (an episode that ran out of steps did not).
        reference_path_m: (R, 3) reference positions for nDTW/SDTW (VLN-CE uses the dense ground-truth
            ``locations``); None skips them.
        shortest_m: L, the geodesic start-goal distance (episode ``info.geodesic_distance``); computed
            with ``geodesic`` when None.
        distances_to_goal_m: precomputed geodesic distance to the goal per trajectory position (saves calls).
    """
    traj = _as_path(trajectory_m, "trajectory")
    goal = np.asarray(goal_m, dtype=np.float64).reshape(-1)
    if goal.shape[0] != traj.shape[1] or not np.all(np.isfinite(goal)):
        raise MetricsError(f"goal {goal_m!r} does not match trajectory dimension {traj.shape[1]}")
    if success_distance_m <= 0:
        raise MetricsError("success_distance_m must be positive")

    if distances_to_goal_m is None:
        d_goal = np.array([_geodesic_or_inf(geodesic, p, goal) for p in traj])
    else:
        if len(distances_to_goal_m) != len(traj):
            raise MetricsError("distances_to_goal_m must have one entry per trajectory position")
        d_goal = np.array([math.inf if d is None else float(d) for d in distances_to_goal_m])
        if np.any(np.isnan(d_goal)):
            raise MetricsError("distances_to_goal_m contains NaN; use None or inf for 'unreachable'")

    if shortest_m is None:
        shortest = float(d_goal[0])
    else:
        shortest = math.inf if not math.isfinite(float(shortest_m)) else float(shortest_m)

    ne = float(d_goal[-1])
    one = float(d_goal.min())
    success = bool(stop_called and ne < success_distance_m)
    oracle_success = bool(one < success_distance_m)
    tl = trajectory_length(traj)

    n_dtw = s_dtw = None
    if reference_path_m is not None:
        ref = _as_path(reference_path_m, "reference path")
        n_dtw = ndtw(
            dedupe_consecutive(traj), ref, success_distance_m=success_distance_m, method=dtw_method
        )
        s_dtw = float(success) * n_dtw

    return EpisodeMetrics(
        ne_m=ne if math.isfinite(ne) else None,
        success=success,
        oracle_success=oracle_success,
        oracle_ne_m=one if math.isfinite(one) else None,
        tl_m=tl,
        spl=spl(success, shortest, tl),
        ndtw=n_dtw,
        sdtw=s_dtw,
        shortest_m=shortest if math.isfinite(shortest) else None,
        stop_called=bool(stop_called),
        steps=len(traj) - 1,
        goal_reachable=math.isfinite(ne),
    )


@dataclass(frozen=True)
class MetricsSummary:
    """Means over episodes, VLN-CE style (rates as fractions; multiply by 100 for tables)."""

    episodes: int
    ne_m: float | None  # mean over episodes whose goal was reachable at the end
    osr: float
    sr: float
    spl: float
    ndtw: float | None
    sdtw: float | None
    tl_m: float
    steps: float
    unreachable: int  # episodes that ended where the goal cannot be reached (excluded from NE)
    extra: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    def as_percent_row(self) -> dict[str, float | int | None]:
        """The row of a results table: NE/TL in metres, rates in percent (as the paper's tables)."""

        def pct(v: float | None) -> float | None:
            return None if v is None else round(100.0 * v, 1)

        return {
            "episodes": self.episodes,
            "NE": None if self.ne_m is None else round(self.ne_m, 2),
            "OSR": pct(self.osr),
            "SR": pct(self.sr),
            "SPL": pct(self.spl),
            "nDTW": pct(self.ndtw),
            "SDTW": pct(self.sdtw),
            "TL": round(self.tl_m, 2),
            "unreachable": self.unreachable,
        }


def summarize(results: Iterable[EpisodeMetrics]) -> MetricsSummary:
    """Average per-episode metrics; an empty input is an error rather than a row of NaNs."""
    res = list(results)
    if not res:
        raise MetricsError("cannot summarise zero episodes")
    reachable = [r.ne_m for r in res if r.ne_m is not None]
    with_dtw = [r for r in res if r.ndtw is not None]
    return MetricsSummary(
        episodes=len(res),
        ne_m=float(np.mean(reachable)) if reachable else None,
        osr=float(np.mean([r.oracle_success for r in res])),
        sr=float(np.mean([r.success for r in res])),
        spl=float(np.mean([r.spl for r in res])),
        ndtw=float(np.mean([r.ndtw for r in with_dtw])) if with_dtw else None,
        sdtw=float(np.mean([r.sdtw for r in with_dtw])) if with_dtw else None,
        tl_m=float(np.mean([r.tl_m for r in res])),
        steps=float(np.mean([r.steps for r in res])),
        unreachable=len(res) - len(reachable),
    )
