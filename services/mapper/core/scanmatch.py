"""Planar scan matching: the mapper's horizontal scans registered to a model of earlier ones.

Shared by the online localiser (localise.py: each panorama against the model of the ones before it)
and the pose graph (posegraph.py: each panorama's scan against another's). A scan is (N, 3) rows of
(x, y, standard error) in the robot frame; the model keeps, per cell and height level, the mean point
and the direction it was seen from; the matcher is point-to-line ICP on (x, y, heading) with Cauchy
weights and an optional odometry prior. ``cfg`` is the localiser's config (its ICP and judge's
thresholds), read by attribute.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from shared.geometry import wrap_angle


@dataclass(frozen=True)
class Match:
    """One registration's outcome: the pose found and how far to trust it."""

    xy_m: np.ndarray
    heading_rad: float
    rays: int  # the scan's rays
    inliers: int
    fitness: float  # inliers / rays
    rmse_m: float  # of the inliers' point-to-line residuals
    constraint: float  # the weakest direction's share of the information (0: degenerate)
    weak_dir: np.ndarray  # (2,) unit vector of the translation the scan pins least


def rot(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


@dataclass
class ScanModel:
    """Scan points in the map frame, averaged per cell and height level, with the mean direction
    they were seen from: a wall's two faces lie a hand apart, and a scan of a new room must not match
    its side of the wall to the face seen from the room before (it pulled poses by the wall's
    thickness, and the errors grew instead of shrinking)."""

    cell_m: float
    codes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # sorted cell codes
    version: int = 0  # bumped by every add (what was derived from the model is stale)
    sums: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # (wx, wy, wz, w, svx, svy) per cell

    def add(self, pts: np.ndarray, origin_xy: np.ndarray, z_m: float, weight: np.ndarray) -> None:
        """Points averaged by ``weight`` (inverse variance): a far, noisy ray moves a cell little."""
        view = origin_xy - pts
        view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-9)
        ij = np.floor(pts / self.cell_m).astype(np.int64) + CODE_BIAS
        level = int(round(z_m / 0.25)) + CODE_BIAS
        code = (ij[:, 0] << 42) | (ij[:, 1] << 21) | level
        w = np.asarray(weight, np.float64)
        rows = np.column_stack([pts * w[:, None], np.full(len(pts), z_m) * w, w, view])
        codes, inv = np.unique(np.concatenate([self.codes, code]), return_inverse=True)
        sums = np.zeros((len(codes), 6))
        np.add.at(sums, inv, np.concatenate([self.sums, rows]))
        self.codes, self.sums = codes, sums
        self.version += 1

    def near(self, xy: np.ndarray, z_m: float, radius_m: float, same_level_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(points, mean view directions) seen from within ``same_level_m`` of ``z_m``, near ``xy``."""
        a = self.sums
        p = a[:, :3] / np.maximum(a[:, 3:4], 1e-300)
        sel = (np.abs(p[:, 2] - z_m) <= same_level_m) & (np.hypot(p[:, 0] - xy[0], p[:, 1] - xy[1]) <= radius_m)
        return p[sel, :2], a[sel, 4:6]


CODE_BIAS = 1 << 20  # cell indices of +-1,000,000 cells: 31 km at 3 cm


def line_normals(pts: np.ndarray, view: np.ndarray, radius_m: float, max_ratio: float,
                  k: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """(points on a line, their unit normals facing where they were seen from): PCA of each point's
    ``k`` nearest neighbours within ``radius_m`` (at least 4)."""
    if len(pts) < 4:
        return np.zeros((0, 2)), np.zeros((0, 2))
    d, j = cKDTree(pts).query(pts, k=min(k, len(pts)), distance_upper_bound=radius_m)
    m = np.isfinite(d)
    q = np.where(m[..., None], pts[np.minimum(j, len(pts) - 1)], 0.0)
    cnt = m.sum(axis=1)
    mean = q.sum(axis=1) / cnt[:, None]
    dq = np.where(m[..., None], q - mean[:, None, :], 0.0)
    sxx, syy, sxy = (dq[..., 0] ** 2).sum(1), (dq[..., 1] ** 2).sum(1), (dq[..., 0] * dq[..., 1]).sum(1)
    # Eigenvalues of the 2x2 scatter in closed form; the normal is the smaller one's eigenvector.
    tr, det = sxx + syy, sxx * syy - sxy**2
    disc = np.sqrt(np.maximum(tr**2 / 4.0 - det, 0.0))
    lo, hi = tr / 2.0 - disc, tr / 2.0 + disc
    n = np.stack([sxy, lo - sxx], axis=1)
    alt = np.stack([lo - syy, sxy], axis=1)
    n = np.where((np.abs(n).sum(1) >= np.abs(alt).sum(1))[:, None], n, alt)
    norm = np.linalg.norm(n, axis=1)
    ok = (cnt >= 4) & (hi > 0) & (lo <= max_ratio * hi) & (norm > 1e-12)
    n = n[ok] / norm[ok, None]
    n *= np.where(np.einsum("ij,ij->i", n, view[ok]) >= 0, 1.0, -1.0)[:, None]
    return pts[ok], n


def facing(q: np.ndarray, n: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Model points whose face looks towards the robot at ``xy`` (the robot cannot see a wall's back)."""
    return np.einsum("ij,ij->i", n, xy - q) > 0.0


def fit_cost(scan: np.ndarray, model_pts: np.ndarray, model_normals: np.ndarray, xy: np.ndarray, heading: float,
             cfg: Any, tree: cKDTree | None = None) -> float:
    """Mean robust (Cauchy) point-to-line cost of the scan at a pose, a ray with no facing model point
    within the final correspondence distance costing as much as one that far off: what a pose must
    lower to replace another (ICP slides downhill from its seed, sometimes into a wrong basin)."""
    tree = tree if tree is not None else cKDTree(model_pts)
    p = scan[:, :2] @ rot(heading).T + xy
    d, j = tree.query(p, distance_upper_bound=cfg.match_m[1])
    m = np.isfinite(d)
    m[m] = facing(model_pts[j[m]], model_normals[j[m]], xy)
    r = np.full(len(p), cfg.match_m[1])
    if m.any():
        r[m] = np.minimum(np.abs(np.einsum("ij,ij->i", model_normals[j[m]], p[m] - model_pts[j[m]])), cfg.match_m[1])
    return float(np.mean(np.log1p((r / cfg.cauchy_m) ** 2)))


def register(scan: np.ndarray, model_pts: np.ndarray, model_normals: np.ndarray, xy0: np.ndarray,
             heading0: float, cfg: Any, prior_sigma: tuple[float, float] | None = None,
             tree: cKDTree | None = None, min_inliers: int | None = None) -> Match | None:
    """Point-to-line ICP of ``scan`` (robot frame) against the model, from the pose (xy0, heading0);
    with ``prior_sigma`` (m, rad) that pose is also a prior of that uncertainty. ``tree`` (of
    ``model_pts``) and ``min_inliers`` (default ``cfg.min_inliers``) serve a partial scan's caller."""
    min_inliers = cfg.min_inliers if min_inliers is None else min_inliers
    prior = np.zeros((3, 3)) if prior_sigma is None else np.diag(
        [prior_sigma[0] ** -2, prior_sigma[0] ** -2, prior_sigma[1] ** -2])
    x0 = np.array([xy0[0], xy0[1], heading0], np.float64)
    if len(scan) < min_inliers or len(model_pts) < min_inliers:
        return None
    scan, err = scan[:, :2], scan[:, 2]
    # Rays weigh alike: weighting them by their own spread (few band pixels look precise by chance)
    # doubled the median error on generated:0 (1.4 -> 3.8 cm against an exact model).
    ray_var = np.full(len(err), cfg.ray_sigma_m**2)
    cauchy = np.full(len(err), cfg.cauchy_m)
    tree = tree if tree is not None else cKDTree(model_pts)
    xy, th = np.asarray(xy0, np.float64).copy(), float(heading0)
    info = np.zeros((3, 3))
    for it in range(cfg.iterations):
        # Correspondences tighten over the first iterations, then it runs to convergence.
        frac = min(1.0, it / cfg.tighten_iterations)
        dmax = cfg.match_m[0] + (cfg.match_m[1] - cfg.match_m[0]) * frac
        p = scan @ rot(th).T + xy
        d, j = tree.query(p, distance_upper_bound=dmax)
        m = np.isfinite(d)
        m[m] = facing(model_pts[j[m]], model_normals[j[m]], xy)
        if m.sum() < min_inliers:
            return None
        n = model_normals[j[m]]
        res = np.einsum("ij,ij->i", n, p[m] - model_pts[j[m]])
        lever = p[m] - xy
        jac = np.stack([n[:, 0], n[:, 1], n[:, 1] * lever[:, 0] - n[:, 0] * lever[:, 1]], axis=1)
        wgt = 1.0 / (1.0 + (res / cauchy[m]) ** 2) / ray_var[m]
        info = (jac * wgt[:, None]).T @ jac
        g = (jac * wgt[:, None]).T @ res
        dev = np.array([xy[0], xy[1], th]) - x0
        dev[2] = float(wrap_angle(dev[2]))
        try:
            delta = -np.linalg.solve(info + prior + 1e-9 * np.eye(3), g + prior @ dev)
        except np.linalg.LinAlgError:
            return None
        xy += delta[:2]
        th += float(delta[2])
        if np.hypot(*delta[:2]) < 1e-5 and abs(delta[2]) < 1e-6 and frac >= 1.0:
            break
    p = scan @ rot(th).T + xy
    d, j = tree.query(p, distance_upper_bound=cfg.match_m[1])
    m = np.isfinite(d)
    m[m] = facing(model_pts[j[m]], model_normals[j[m]], xy)
    res = np.einsum("ij,ij->i", model_normals[j[m]], p[m] - model_pts[j[m]]) if m.any() else np.zeros(0)
    inl = np.abs(res) <= cfg.inlier_m
    # How well the position is pinned: the weaker eigenvalue of the scan's translation information as
    # a share of its trace (0.5: walls every way; 0: a corridor says nothing along itself).
    ev, evec = np.linalg.eigh(info[:2, :2])
    constraint = float(max(ev[0], 0.0) / max(ev.sum(), 1e-12))
    return Match(xy, float(wrap_angle(th)), len(scan), int(inl.sum()), float(inl.sum() / len(scan)),
                 float(np.sqrt(np.mean(res[inl] ** 2))) if inl.any() else math.inf, constraint, evec[:, 0])
