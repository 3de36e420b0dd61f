"""Voxel fusion of coloured, labelled points: centroid position, mean colour, majority label and
mean view direction.

Used both for streaming RGB-D fusion (points arrive frame batch by frame batch) and for the final
merge of regional clouds. Everything is a sort or a bincount over integer voxel keys, so the cost is
a few passes over the points whatever their density. A point's view direction is the unit vector
from it towards the camera that saw it; a voxel keeps the mean of its points' (``view_dirs``), so a
surface seen from one side only points to that side and a thin one seen from both ends up short.
"""

from __future__ import annotations

import numpy as np

from shared.cloud import PointCloud, quantise_view_dirs, view_dirs_unit

from .errors import InputError
from .kernels import AXIS_BITS as _AXIS_BITS
from .kernels import AXIS_HALF as _AXIS_HALF
from .kernels import LABEL_BITS as _LABEL_BITS
from .kernels import LABEL_MAX as _LABEL_MAX

# A voxel key packs three 15-bit signed coordinates (+-16384 voxels per axis from the origin; +-490 m
# at 3 cm) so that a (voxel, label) pair still fits an int64 with 16 bits for the label.


def voxel_cells(xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N, 3) int64 voxel coordinates: float32 binning, the same in every path (array and compiled)."""
    return np.floor(np.asarray(xyz, np.float32) * np.float32(1.0 / voxel_m)).astype(np.int64)


def pack_cells(cx: np.ndarray, cy: np.ndarray, cz: np.ndarray) -> np.ndarray:
    """Packed int64 keys of voxel coordinates already shifted by AXIS_HALF into [0, 2^AXIS_BITS): x in the
    highest bits, so the keys sort in (x, y, z) order (the compiled loops pack theirs the same way)."""
    return (cx << (2 * _AXIS_BITS)) | (cy << _AXIS_BITS) | cz


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(N, 3) int64 shifted voxel coordinates of packed keys (pack_cells' inverse)."""
    mask = (1 << _AXIS_BITS) - 1
    return np.stack([(keys >> (2 * _AXIS_BITS)) & mask, (keys >> _AXIS_BITS) & mask, keys & mask], axis=1)


def voxel_keys(xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """Integer key of the voxel of each point (int64); raises when a point is out of range."""
    cells = voxel_cells(xyz, voxel_m) + _AXIS_HALF
    if cells.size and (cells.min() < 0 or cells.max() >= (1 << _AXIS_BITS)):
        raise InputError(
            f"points span more than +-{_AXIS_HALF * voxel_m:.0f} m from the origin at voxel {voxel_m} m"
        )
    return pack_cells(cells[:, 0], cells[:, 1], cells[:, 2])


class VoxelAccumulator:
    """Sums of positions, colours and view vectors, counts and label votes per voxel, fed in batches.

    ``add`` reduces each batch to its voxels at once (so memory follows the number of voxels, not of
    points); ``cloud`` merges the batches into one :class:`PointCloud`. Labels and view directions
    come out only when every batch had them: a mix would bias the vote or the mean silently.
    """

    def __init__(self, voxel_m: float, min_points: int = 1):
        if not voxel_m > 0:
            raise ValueError(f"voxel_m must be positive, got {voxel_m}")
        self.voxel_m = float(voxel_m)
        self.min_points = int(min_points)
        self._parts: list[tuple[np.ndarray, ...]] = []
        self._votes: list[tuple[np.ndarray, np.ndarray]] = []
        self._labelled: bool | None = None
        self._viewed: bool | None = None
        self.points_in = 0

    def add(self, xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None = None,
            view_units: np.ndarray | None = None) -> None:
        """Add (N, 3) points with (N, 3) uint8 colours, optional (N,) int labels (-1 = unknown) and
        optional (N, 3) float view vectors: the unit vector from each point towards the camera that saw
        it (or, for a cloud being merged, the mean of such vectors that its point already holds)."""
        if len(xyz) == 0:
            return
        labelled = labels is not None
        self._note(labelled, view_units is not None)
        self.points_in += len(xyz)
        dense = _reduce_dense(xyz, rgb, labels if labelled else None, self.voxel_m, view_units)
        if dense is not None:
            part, votes = dense
            self._parts.append(part)
            if labelled:
                self._votes.append(votes)
        else:
            keys = voxel_keys(xyz, self.voxel_m)
            self._parts.append(_reduce(keys, np.asarray(xyz, np.float64), np.asarray(rgb, np.float64), view_units))
            if labelled:
                self._votes.append(_votes(keys, np.asarray(labels)))
        if len(self._parts) >= 16:
            self._compact()

    def add_reduced(self, part: tuple[np.ndarray | None, ...], votes: tuple[np.ndarray, np.ndarray] | None,
                    points: int) -> None:
        """Add a batch already reduced to its voxels (what ``kernels.FrameFuser.result`` gives).

        ``part`` is (keys ascending, position sums (K, 3), colour sums (K, 3), counts (K,), view-vector
        sums (K, 3) or None) and ``votes`` (packed voxel-label keys ascending, counts), or None for an
        unlabelled batch."""
        if points == 0:
            return
        labelled = votes is not None
        self._note(labelled, part[4] is not None)
        self.points_in += int(points)
        self._parts.append(part)
        if labelled:
            self._votes.append(votes)
        if len(self._parts) >= 16:
            self._compact()

    def _note(self, labelled: bool, viewed: bool) -> None:
        """Remember whether every batch so far had labels and view vectors."""
        # Mixing batches with and without would bias the majority vote or the mean direction silently.
        self._labelled = labelled if self._labelled is None else self._labelled and labelled
        self._viewed = viewed if self._viewed is None else self._viewed and viewed

    def _compact(self) -> None:
        if len(self._parts) == 1 and len(self._votes) <= 1:
            return  # one reduced batch is already sorted and unique
        keys = np.concatenate([p[0] for p in self._parts])
        sxyz = np.concatenate([p[1] for p in self._parts])
        srgb = np.concatenate([p[2] for p in self._parts])
        cnt = np.concatenate([p[3] for p in self._parts])
        # Once a batch came without view vectors the cloud has none: their sums need not be kept.
        sview = np.concatenate([p[4] for p in self._parts]) if self._viewed else None
        uk, inv = np.unique(keys, return_inverse=True)
        n = len(uk)
        self._parts = [(
            uk,
            np.stack([np.bincount(inv, sxyz[:, k], n) for k in range(3)], axis=1),
            np.stack([np.bincount(inv, srgb[:, k], n) for k in range(3)], axis=1),
            np.bincount(inv, cnt, n),
            None if sview is None else np.stack([np.bincount(inv, sview[:, k], n) for k in range(3)], axis=1),
        )]
        if self._votes:
            pk = np.concatenate([v[0] for v in self._votes])
            pc = np.concatenate([v[1] for v in self._votes])
            upk, pinv = np.unique(pk, return_inverse=True)
            self._votes = [(upk, np.bincount(pinv, pc, len(upk)))]

    @property
    def voxel_count(self) -> int:
        if not self._parts:
            return 0
        self._compact()
        return len(self._parts[0][0])

    def counts(self) -> np.ndarray:
        """The number of points fused into each voxel of ``cloud`` (same order)."""
        if not self._parts:
            return np.zeros(0)
        self._compact()
        cnt = self._parts[0][3]
        return cnt[cnt >= self.min_points]

    def cloud(self, label_names: dict[int, str] | None = None) -> PointCloud:
        """The fused cloud: one point per voxel with at least ``min_points`` points."""
        if not self._parts:
            return PointCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), None, dict(label_names or {}))
        self._compact()
        keys, sxyz, srgb, cnt, sview = self._parts[0]
        keep = cnt >= self.min_points
        c = cnt[keep][:, None]
        xyz = sxyz[keep] / c
        rgb = np.clip(np.rint(srgb[keep] / c), 0, 255).astype(np.uint8)
        labels = None
        if self._labelled:
            labels = _majority(keys, self._votes[0] if self._votes else None)[keep]
        views = quantise_view_dirs(sview[keep] / c) if self._viewed else None
        return PointCloud(xyz, rgb, labels, dict(label_names or {}), views)


_DENSE_MAX_CELLS = 48_000_000
_DENSE_MAX_VOTES = 64_000_000


def _reduce_dense(xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray | None, voxel_m: float,
                  view_units: np.ndarray | None = None):
    """Sort-free reduction over the batch's bounding box of voxels (bincounts only).

    A batch of frames covers a few metres, so its voxel box is small enough for dense counters;
    this is several times faster than sorting millions of keys. None when the box is too large.
    """
    cells = voxel_cells(xyz, voxel_m)
    lo = cells.min(axis=0)
    hi = cells.max(axis=0)
    dims = hi - lo + 1
    n_cells = int(dims.prod())
    if n_cells > _DENSE_MAX_CELLS or lo.min() < -_AXIS_HALF or hi.max() >= _AXIS_HALF:
        return None
    cells -= lo
    flat = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    cnt = np.bincount(flat, minlength=n_cells)
    occ = np.flatnonzero(cnt)
    k = len(occ)
    lookup = np.zeros(n_cells, np.int32)
    lookup[occ] = np.arange(k, dtype=np.int32)
    inv = lookup[flat]
    # occ is ascending in (x, y, z) order, which is also the order of the packed global keys.
    c = np.stack(np.unravel_index(occ, tuple(dims)), axis=1) + lo + _AXIS_HALF
    keys = pack_cells(c[:, 0], c[:, 1], c[:, 2])
    sxyz = np.stack([np.bincount(inv, xyz[:, j], k) for j in range(3)], axis=1)
    srgb = np.stack([np.bincount(inv, rgb[:, j], k) for j in range(3)], axis=1)
    sview = None if view_units is None else np.stack([np.bincount(inv, view_units[:, j], k) for j in range(3)], axis=1)
    part = (keys, sxyz, srgb, cnt[occ].astype(np.float64), sview)
    if labels is None:
        return part, None
    lab = np.asarray(labels).astype(np.int64)
    known = (lab >= 0) & (lab <= _LABEL_MAX)
    lab_k, inv_k = lab[known], inv[known]
    if len(lab_k) == 0:
        return part, (np.empty(0, np.int64), np.empty(0, np.float64))
    present = np.flatnonzero(np.bincount(lab_k))
    n_lab = len(present)
    if k * n_lab > _DENSE_MAX_VOTES:
        return part, _votes(keys[inv], lab.astype(np.int32))
    remap = np.zeros(present[-1] + 1, np.int64)
    remap[present] = np.arange(n_lab)
    votes = np.bincount(inv_k.astype(np.int64) * n_lab + remap[lab_k], minlength=k * n_lab)
    nz = np.flatnonzero(votes)
    pk = (keys[nz // n_lab] << _LABEL_BITS) | (present[nz % n_lab] + 1)
    return part, (pk, votes[nz].astype(np.float64))


def _reduce(keys: np.ndarray, xyz: np.ndarray, rgb: np.ndarray, view_units: np.ndarray | None = None):
    uk, inv = np.unique(keys, return_inverse=True)
    n = len(uk)
    return (
        uk,
        np.stack([np.bincount(inv, xyz[:, k], n) for k in range(3)], axis=1),
        np.stack([np.bincount(inv, rgb[:, k], n) for k in range(3)], axis=1),
        np.bincount(inv, minlength=n).astype(np.float64),
        None if view_units is None else np.stack([np.bincount(inv, view_units[:, k], n) for k in range(3)], axis=1),
    )


def _votes(keys: np.ndarray, labels: np.ndarray):
    labels = labels.astype(np.int64)
    known = (labels >= 0) & (labels <= _LABEL_MAX)
    pk = (keys[known] << _LABEL_BITS) | (labels[known] + 1)
    upk, cnt = np.unique(pk, return_counts=True)
    return upk, cnt.astype(np.float64)


def _majority(voxel_keys_sorted: np.ndarray, votes) -> np.ndarray:
    out = np.full(len(voxel_keys_sorted), -1, np.int32)
    if votes is None or len(votes[0]) == 0:
        return out
    pk, cnt = votes
    vk = pk >> _LABEL_BITS
    lab = (pk & ((1 << _LABEL_BITS) - 1)) - 1
    # Pairs are sorted by voxel then label; the last of each voxel after sorting by count wins
    # (ties go to the larger label id, deterministically).
    order = np.lexsort((lab, cnt, vk))
    vk, lab = vk[order], lab[order]
    last = np.r_[vk[1:] != vk[:-1], True]
    pos = np.searchsorted(voxel_keys_sorted, vk[last])
    out[pos] = lab[last]
    return out


def voxel_downsample(cloud: PointCloud, voxel_m: float, min_points: int = 1) -> PointCloud:
    """One point per occupied voxel (centroid, mean colour, majority label, mean view direction)."""
    acc = VoxelAccumulator(voxel_m, min_points)
    # The points' view directions are already means of unit vectors: their mean is kept unnormalised,
    # so a voxel merging points seen from opposite sides ends short, as fusion would make it.
    views = None if cloud.view_dirs is None else view_dirs_unit(cloud.view_dirs)
    acc.add(cloud.xyz, cloud.rgb, cloud.labels, views)
    out = acc.cloud(cloud.label_names)
    if cloud.labels is None:
        out.labels = None
    return out
