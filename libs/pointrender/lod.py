"""Precomputed point level of detail: voxel-averaged levels per spatial block, chosen per view by
the projected size of a level's cell.

This is the layered point LOD of Potree / Wimmer and Scheiblauer 2006 ("Instant Points: fast
rendering of unprocessed point clouds"), with the per-block selection of sequential point trees
(Dachsbacher, Vogelgsang and Stamminger 2003): level ``L >= 1`` replaces the points of each
``cell_m * 2^(L-1)`` voxel of a block by one point at their mean position with their mean colour
(and the label of the member nearest that mean); a view draws each block at the coarsest level
whose cell still projects to at most ``cell_px`` pixels at the block's nearest point. A view then
draws about one point per covered pixel per depth layer, whatever the density of the map and
however far it reaches, instead of every point in the frustum; and because each level point is
the average of what it stands for, a distant wall keeps its mean colour (prefiltering, as a
texture's mip level does), which a random subsample of the same size does not.

Levels are stored after the original points in one cloud, grouped by block like the original, so
that a view's selection is a list of contiguous runs, exactly what the splat's front pass walks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from shared.cloud import PointCloud
from shared.jit import AVAILABLE, kernel
from libs.pointrender.cloud import IndexedCloud


@dataclass(frozen=True)
class VoxelLod:
    """Level 0 (the index's points) followed by the voxel levels 1..L, one cloud.

    Block ``b`` at level ``L`` is ``cloud[starts[L, b] : starts[L, b] + counts[L, b]]``; ``spacing``
    is the local spacing of every point of ``cloud`` (level 0: measured; level L: the larger of
    the cell and its members' mean spacing)."""

    cloud: PointCloud
    starts: np.ndarray  # int64 (L + 1, B)
    counts: np.ndarray  # int64 (L + 1, B)
    cell_m: tuple[float, ...]  # cell of each level (level 0: 0.0)
    spacing: np.ndarray  # float32 (len(cloud),)
    # Unit normal of every point of ``cloud`` (None: not built); level L: the principal axis of its
    # members' normals (the mean of n n^T, which does not depend on their signs).
    normals: np.ndarray | None = None  # float32 (len(cloud), 3)
    # Whether a point's normal points towards the side the robot saw (None: no side is known).
    # Level L: where the mean of its members' sided normals (0 for the others) lies at least
    # SIDE_AGREEMENT along its axis, which is then turned that way: most members agree.
    sided: np.ndarray | None = None  # uint8 (len(cloud),)

    @property
    def levels(self) -> int:
        return len(self.cell_m) - 1

    def select(self, index: IndexedCloud, mask: np.ndarray | None, world_from_camera: np.ndarray,
               focal_px: float, cell_px: float) -> tuple[np.ndarray, np.ndarray]:
        """(starts, counts) of the runs a view draws: each block of ``mask`` (None: all) at the
        coarsest level whose cell projects to at most ``cell_px`` pixels at its nearest point."""
        cam = np.ascontiguousarray(world_from_camera[:3, 3], np.float64)
        if select_runs is not None:  # the same arithmetic block by block, without ~10 array temporaries
            every = mask is None
            mask = np.ones(1, bool) if every else mask
            starts = np.empty(index.block_count if every else int(np.count_nonzero(mask)), np.int64)
            counts = np.empty_like(starts)
            select_runs(mask, every, index.block_min, index.block_max, cam, float(focal_px), float(cell_px),
                        float(self.cell_m[1]), self.levels, self.starts, self.counts, starts, counts)
            return starts, counts
        blocks = np.arange(index.block_count) if mask is None else np.flatnonzero(mask)
        gap = np.maximum(np.maximum(index.block_min[blocks] - cam, cam - index.block_max[blocks]), 0.0)
        dist = np.linalg.norm(gap, axis=1)
        need_m = cell_px * dist / focal_px
        # cell_L = cell_1 * 2^(L-1) <= need  <=>  L <= log2(need / cell_1) + 1
        with np.errstate(divide="ignore"):
            level = np.floor(np.log2(np.maximum(need_m, 1e-12) / self.cell_m[1])).astype(np.int64) + 1
        level = np.clip(level, 0, self.levels)
        return self.starts[level, blocks], self.counts[level, blocks]


def first_cell_m(spacing: np.ndarray, cell_m: float, min_spacings: float) -> float:
    """Level 1's cell for a cloud of point ``spacing``: ``cell_m`` halved while it stays at least
    ``min_spacings`` times the cloud's median spacing. A level whose cells are no wider than the
    points' own spacing merges nothing, so a cloud's first level should be a little coarser than the
    cloud, whatever its density: a scan at 1 cm would otherwise draw every point up to the distance
    where ``cell_m`` reaches the pixel budget."""
    median = float(np.median(spacing)) if len(spacing) else cell_m
    cell = float(cell_m)
    while cell / 2.0 >= min_spacings * median:
        cell /= 2.0
    return cell


SIDE_AGREEMENT = 0.5


@dataclass(frozen=True)
class VoxelGeometry:
    """The voxel levels of an index without normals (``lod``), and how each level groups the one
    below (``groups[L - 1]``: the voxel of level L of every point of level L - 1; ``sizes[L - 1]``:
    the number of original points in each voxel of level L).

    What follows from positions, colours, labels and spacing is the same whatever normals a renderer
    asks for (modes, slope tolerance, sides), so it is built once per (cell, levels) and the normals
    of each setting are summed over the same groups (:meth:`with_normals`). The groups cost one
    integer per point of the levels they group (8 MB for a 1e6-point map)."""

    lod: VoxelLod
    groups: tuple[np.ndarray, ...]  # intp (points of level L - 1,) per level L >= 1
    sizes: tuple[np.ndarray, ...]  # float64 (voxels of level L,) per level L >= 1

    def with_normals(self, normals: np.ndarray, sided: np.ndarray | None = None) -> VoxelLod:
        """The LOD with ``normals`` (and ``sided``) per point of the index and their levels'.

        Each level sums its members' n n^T (and sided normals) over the voxels of the level below,
        carrying sums, so its axes are those of all its original points."""
        n64 = normals.astype(np.float64)
        # Sums of n n^T (xx, yy, zz, xy, xz, yz): a level's normal is their principal axis.
        s_nn = np.stack([n64[:, a] * n64[:, b] for a, b in _NN], 1)
        s_side = None if sided is None else n64 * (sided != 0)[:, None]  # sums of the sided members' normals
        parts_n, parts_sided = [], []
        for inv, n in zip(self.groups, self.sizes):
            m = len(n)
            s_nn = np.stack([np.bincount(inv, weights=s_nn[:, k], minlength=m) for k in range(6)], 1)
            axis = _principal_axis(s_nn)
            if s_side is not None:
                s_side = np.stack([np.bincount(inv, weights=s_side[:, k], minlength=m) for k in range(3)], 1)
                agree = np.einsum("ij,ij->i", axis.astype(np.float64), s_side) / n
                axis = np.where((agree < 0)[:, None], -axis, axis)
                parts_sided.append((np.abs(agree) >= SIDE_AGREEMENT).astype(np.uint8))
            parts_n.append(axis)
        all_sided = None if sided is None else np.concatenate([sided.astype(np.uint8), *parts_sided])
        return replace(self.lod, normals=np.concatenate([normals.astype(np.float32), *parts_n]), sided=all_sided)


def build_voxel_lod(index: IndexedCloud, spacing: np.ndarray, cell_m: float, levels: int,
                    normals: np.ndarray | None = None, sided: np.ndarray | None = None) -> VoxelLod:
    """The voxel levels of ``index`` (``spacing``, and optional ``normals`` with ``sided``: per point
    of ``index.cloud``, as :func:`visibility.orient_normals` gives them)."""
    geometry = build_voxel_geometry(index, spacing, cell_m, levels)
    return geometry.lod if normals is None else geometry.with_normals(normals, sided)


def build_voxel_geometry(index: IndexedCloud, spacing: np.ndarray, cell_m: float, levels: int) -> VoxelGeometry:
    """The voxel levels of ``index`` without normals, and their groups (:class:`VoxelGeometry`).

    Each level is built from the one below (a cell of level L is exactly the union of 2x2x2 cells
    of level L - 1 on the same grid), carrying sums and counts, so its means are exact and the
    build costs about one pass over the cloud plus one over each smaller level."""
    cloud = index.cloud
    lo = cloud.xyz.astype(np.float64).min(axis=0)
    n_blocks = index.block_count
    # The current level as voxels: block, integer cell, point count, sums of xyz / rgb / spacing,
    # and a representative (position, label) for the label of the next level.
    blk = np.repeat(np.arange(n_blocks, dtype=np.int64), index.counts)
    xyz = cloud.xyz.astype(np.float64)
    cnt = np.ones(len(cloud), np.float64)
    s_xyz, s_rgb, s_sp = xyz, cloud.rgb.astype(np.float64), spacing.astype(np.float64)
    rep_xyz, rep_lab = xyz, cloud.labels
    cell_xyz = np.floor((xyz - lo) / cell_m).astype(np.int64)  # level-1 cells of the points
    parts_xyz, parts_rgb, parts_lab, parts_sp = [], [], [], []
    groups, sizes = [], []
    starts = [index.starts.astype(np.int64)]
    counts = [index.counts.astype(np.int64)]
    cells = [0.0]
    offset = len(cloud)
    for lev in range(1, levels + 1):
        cell = cell_m * 2 ** (lev - 1)
        if lev > 1:
            cell_xyz = cell_xyz // 2  # floor(floor(x / c) / 2) == floor(x / 2c)
        dims = cell_xyz.max(axis=0) + 1
        key = ((blk * dims[0] + cell_xyz[:, 0]) * dims[1] + cell_xyz[:, 1]) * dims[2] + cell_xyz[:, 2]
        uniq, inv = np.unique(key, return_inverse=True)
        m = len(uniq)

        def total(a):
            return np.bincount(inv, weights=a, minlength=m)

        n = total(cnt)
        t_xyz = np.stack([total(s_xyz[:, k]) for k in range(3)], 1)
        t_rgb = np.stack([total(s_rgb[:, k]) for k in range(3)], 1)
        t_sp = total(s_sp)
        groups.append(inv)
        sizes.append(n)
        mean = t_xyz / n[:, None]
        if rep_lab is not None:
            # The label of the member nearest the voxel's mean: a voxel on the edge between two
            # objects takes the one its point stands on.
            d2 = ((rep_xyz - mean[inv]) ** 2).sum(axis=1)
            order = np.lexsort((d2, inv))
            first = order[np.concatenate([[0], np.flatnonzero(np.diff(inv[order])) + 1])]
            rep_xyz, rep_lab = rep_xyz[first], rep_lab[first]
            parts_lab.append(rep_lab.astype(np.int32))
        parts_xyz.append(mean.astype(np.float32))
        parts_rgb.append(np.clip(np.rint(t_rgb / n[:, None]), 0, 255).astype(np.uint8))
        parts_sp.append(np.maximum(t_sp / n, cell).astype(np.float32))
        # Voxel keys sort by block first: each block's voxels are one run.
        blk = uniq // (dims[0] * dims[1] * dims[2])
        per_block = np.bincount(blk, minlength=n_blocks).astype(np.int64)
        starts.append(offset + np.concatenate([[0], np.cumsum(per_block)[:-1]]).astype(np.int64))
        counts.append(per_block)
        cells.append(cell)
        offset += m
        # The next level groups these voxels: their cells, decoded from their keys.
        cell_xyz = np.stack([(uniq // (dims[1] * dims[2])) % dims[0], (uniq // dims[2]) % dims[1], uniq % dims[2]], 1)
        cnt, s_xyz, s_rgb, s_sp = n, t_xyz, t_rgb, t_sp
    labels = None if cloud.labels is None else np.concatenate([cloud.labels.astype(np.int32), *parts_lab])
    full = PointCloud(np.concatenate([cloud.xyz.astype(np.float32), *parts_xyz]),
                      np.concatenate([cloud.rgb, *parts_rgb]), labels, cloud.label_names)
    lod = VoxelLod(full, np.stack(starts), np.stack(counts), tuple(cells),
                   np.concatenate([spacing.astype(np.float32), *parts_sp]))
    return VoxelGeometry(lod, tuple(groups), tuple(sizes))


_NN = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _principal_axis(s_nn: np.ndarray) -> np.ndarray:
    """float32 (M, 3) unit principal axes of the symmetric matrices given by their six sums."""
    m = np.empty((len(s_nn), 3, 3))
    for k, (a, b) in enumerate(_NN):
        m[:, a, b] = m[:, b, a] = s_nn[:, k]
    _, vec = np.linalg.eigh(m)  # ascending eigenvalues: the last column is the principal axis
    return vec[:, :, 2].astype(np.float32)


def _select_runs(mask, every, block_min, block_max, cam, focal_px, cell_px, cell1, levels, starts, counts,
                 out_starts, out_counts):
    """:meth:`VoxelLod.select` block by block (the blocks of ``mask``, or all with ``every``):
    the same float64 operations in the same order (the gap per axis, its norm, the level)."""
    n = 0
    for b in range(block_min.shape[0]):
        if not every and not mask[b]:
            continue
        g0 = max(max(block_min[b, 0] - cam[0], cam[0] - block_max[b, 0]), 0.0)
        g1 = max(max(block_min[b, 1] - cam[1], cam[1] - block_max[b, 1]), 0.0)
        g2 = max(max(block_min[b, 2] - cam[2], cam[2] - block_max[b, 2]), 0.0)
        dist = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        need = cell_px * dist / focal_px
        level = np.int64(np.floor(np.log2(max(need, 1e-12) / cell1))) + 1
        level = min(max(level, 0), levels)
        out_starts[n] = starts[level, b]
        out_counts[n] = counts[level, b]
        n += 1


select_runs = kernel()(_select_runs) if AVAILABLE else None
