"""The human-curated cloud of the paper's ablation: points sampled from the scene mesh itself.

The paper compares its agent-reconstructed cloud with the dataset's curated one; in our setting the
curated cloud is an area-uniform, stratified sample of the scene's surfaces (evenly spread, as a
scanner's points are, not clumped as independent random samples are) with their true colours and
semantic labels, i.e. a reconstruction with no pose, scale or depth error
(:func:`~shared.cloud.sample_mesh` does the sampling).

Only surfaces that can be seen from walkable space are kept (a scanned dataset holds what its
cameras saw): a sample stays when the straight line to it from one of its nearest viewpoints -
walkable floor points, on a coarse grid, at a few eye heights - is free. Ceiling interiors, the
tops of slabs, the inside of walls and the faces hidden under furniture go; they would otherwise
be a third of the points, and a view rendered from the map would show them through every gap.
"""

from __future__ import annotations

import numpy as np

from evaluation.errors import ConfigError
from shared.cloud import PointCloud, quantise_view_dirs, sample_mesh


# A curated cloud as dense as a built map: about one point per cell of the reconstructor's 3 cm voxel
# grid (1 / 0.03^2 = 1111 per m2). At 300 per m2 (random samples ~6 cm apart) the renderer's footprints,
# sized from the local spacing, left 6 % holes and a 3 % leak within 1 m of a wall on generated:0,
# where a built map has neither (bench.anticipation, curated row); at 1000 (96 free poses): holes
# <= 0.5 %, SSIM 0.90-0.95, leak <= 0.1 % beyond 1 m but still 1.6 % within it, in the gaps random
# samples leave. The samples are stratified (sample_mesh): that leak is 0.3 %, holes <= 0.1 %, labels
# 97.6-98.3 %, SSIM 0.909 / 0.935 / 0.915 (0.901 / 0.946 / 0.937 random; the wider, even spacing gives
# wider footprints), every target met at free poses and candidates.
CURATED_DENSITY_PER_M2 = 1000.0


def sample_scene_cloud(scene, *, density_per_m2: float = CURATED_DENSITY_PER_M2, max_points: int = 1_000_000,
                       seed: int = 0, visible_only: bool = True, viewpoints_m: np.ndarray | None = None,
                       eye_heights_m: tuple[float, ...] = (0.6, 1.25), viewpoint_grid_m: float = 0.5,
                       nearest_viewpoints: int = 12) -> PointCloud:
    """A cloud of ``density_per_m2`` points per square metre of the scene's visible surfaces (at
    most ``max_points``), labels and label names kept.

    With ``visible_only`` (default) a sample is kept only when one of its ``nearest_viewpoints``
    nearest viewpoints sees it: ``viewpoints_m`` (M, 3), or walkable floor points of the scene's
    navigation grid thinned to one per ``viewpoint_grid_m`` cell, raised by each of ``eye_heights_m``;
    its ``view_dirs`` are then the mean direction towards the viewpoints that see it (as a built
    map's are towards its cameras), so the renderer knows which side of a wall was in view."""
    if density_per_m2 <= 0 or max_points < 1:
        raise ConfigError("density_per_m2 and max_points must be positive")
    corners = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles, np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    n = max(1, round(float(area) * density_per_m2))

    def sample(n_points: int) -> PointCloud:
        return sample_mesh(scene.vertices, scene.triangles, scene.vertex_colors, scene.triangle_labels,
                           n_points=n_points, seed=seed, texture=scene.texture, label_names=scene.label_names,
                           stratified=True)

    if not visible_only:
        return sample(int(min(max_points, n)))
    if viewpoints_m is None:
        viewpoints_m = walkable_viewpoints(scene, eye_heights_m, viewpoint_grid_m)

    def visible_sample(n_points: int):
        cloud = sample(n_points)
        seen, towards = visible_from(scene, cloud.xyz, viewpoints_m, nearest_viewpoints, with_dirs=True)
        return cloud, seen, towards

    # Sample the whole surface at the density asked for, then keep the visible part: the visible
    # surfaces get that density (up to max_points, as much again of candidates at most).
    cloud, seen, towards = visible_sample(int(min(2 * max_points, n)))
    if seen.sum() > max_points:
        # Over the cap (a large mesh): sample again at the density that leaves about max_points
        # visible. Thinning the stratified sample at random would bring back the clumps and gaps
        # that stratifying removed (on a 1 m wall, the largest empty circle 3.4 -> 4.5-6.1 cm).
        cloud, seen, towards = visible_sample(int(len(cloud) * max_points / seen.sum()))
    cloud.view_dirs = quantise_view_dirs(towards)
    keep = np.flatnonzero(seen)
    if len(keep) > max_points:  # the second sample's visible share differs by a few points
        keep = np.sort(np.random.default_rng(seed).choice(keep, max_points, replace=False))
    return cloud.subset(keep)


def walkable_viewpoints(scene, eye_heights_m=(0.6, 1.25), grid_m: float = 0.5) -> np.ndarray:
    """(M, 3) eye positions over the scene's walkable floor: one node per ``grid_m`` cell and floor
    level (the navigation grid's nodes), raised by each eye height."""
    from libs.world.navgrid import NavGrid

    nodes = np.asarray(NavGrid(scene).nodes_m, np.float64)
    if len(nodes) == 0:
        raise ConfigError("the scene has no walkable floor to see its surfaces from")
    cell = np.floor(nodes / np.array([grid_m, grid_m, 0.5])).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    floor = nodes[np.sort(first)]
    return np.concatenate([floor + np.array([0.0, 0.0, h]) for h in eye_heights_m])


def visible_from(scene, xyz: np.ndarray, viewpoints_m: np.ndarray, nearest: int = 12,
                 clearance_m: float = 0.02, chunk: int = 16_384, with_dirs: bool = False):
    """Boolean mask of the points (on the scene's surfaces) that one of their ``nearest``
    viewpoints sees: the segment from the viewpoint stops ``clearance_m`` short of the point
    without hitting the mesh. ``with_dirs``: also the mean of the unit vectors from each point
    towards the viewpoints that see it (float (N, 3); zero where none does).

    Points go ``chunk`` at a time (each point's answer is its own, so the chunk changes no bit): 16k
    points make ~5 MB temporaries, 200k made ~57 MB ones whose fresh pages the kernel had to fault in
    (300k points on generated:0: 4.4 s of system CPU on the first call, against 0.02 s at 16k)."""
    from shared.o3d import o3d
    from scipy.spatial import cKDTree

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(np.asarray(scene.vertices, np.float32)),
                     o3d.core.Tensor(np.asarray(scene.triangles, np.uint32)))
    vp = np.asarray(viewpoints_m, np.float64)
    k = min(nearest, len(vp))
    tree = cKDTree(vp)
    seen = np.zeros(len(xyz), bool)
    towards = np.zeros((len(xyz), 3)) if with_dirs else None
    for a in range(0, len(xyz), chunk):
        pts = np.asarray(xyz[a : a + chunk], np.float64)
        _, nn = tree.query(pts, k=k, workers=-1)
        nn = nn.reshape(len(pts), k)
        origin = vp[nn]  # (n, k, 3)
        d = pts[:, None, :] - origin
        dist = np.linalg.norm(d, axis=-1)
        rays = np.concatenate([origin, d], axis=-1).reshape(-1, 6).astype(np.float32)
        t = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(len(pts), k)
        # t is in units of the segment: the point itself is at t = 1.
        sees = t * dist >= dist - clearance_m
        seen[a : a + chunk] = sees.any(axis=1)
        if with_dirs:
            unit = -d / np.maximum(dist, 1e-9)[..., None]
            towards[a : a + chunk] = (unit * sees[..., None]).sum(axis=1) / np.maximum(sees.sum(axis=1), 1)[:, None]
    return (seen, towards) if with_dirs else seen
