"""The torch array backend of the splatting renderer (``_TorchOps``: CUDA when available, else
CPU); the same operations as :mod:`ops_numpy`, equal within float tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from libs.pointrender.cloud import IndexedCloud
from libs.pointrender.errors import BackendUnavailableError

from libs.pointrender.ops_numpy import _CloudArrays, _index_grid


class _TorchOps:
    name = "torch"
    # torch parallelises inside each op (and a GPU serialises kernels): one view at a time.
    concurrent_views = False

    def __init__(self, device: str):
        import torch

        self.torch = torch
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise BackendUnavailableError(f"torch device {device!r} requested but CUDA is unavailable")
        self.device = torch.device(device)
        self._grids: dict = {}

    def asarray(self, a: np.ndarray):
        return self.torch.from_numpy(np.ascontiguousarray(a)).to(self.device)

    def to_numpy(self, a) -> np.ndarray:
        return a.detach().cpu().numpy()

    def full(self, n: int, value: float):
        return self.torch.full((n,), value, dtype=self.torch.float32, device=self.device)

    def scatter_min(self, n: int, idx, vals):
        out = self.full(n, math.inf)
        return out.scatter_reduce_(0, idx, vals, "amin", include_self=True)

    def scatter_max_int(self, n: int, idx, vals):
        out = self.torch.full((n,), -1, dtype=self.torch.int64, device=self.device)
        return out.scatter_reduce_(0, idx, vals, "amax", include_self=True)

    def scatter_add(self, n: int, idx, cols: Sequence):
        torch = self.torch
        src = torch.stack(list(cols), dim=1)
        out = torch.zeros((n, src.shape[1]), dtype=torch.float32, device=self.device)
        out.index_add_(0, idx, src)
        return list(out.unbind(1))

    def sum_in_order(self, n: int, idx, vals):
        # float32 sums as the numpy backend's, but index_add_ does not promise their order: the
        # backends agree within the tests' tolerance, not to the bit.
        out = self.torch.zeros(n, dtype=self.torch.float32, device=self.device)
        return out.index_add_(0, idx, vals.to(self.torch.float32))

    def accumulate_front(self, n: int, q, front, z, arrays: _CloudArrays, idx, qu, qv, spacing=None,
                         unseen=None, unseen_rgb=(0, 0, 0)):
        torch = self.torch
        lq = q[front]
        pts = idx[front]
        rgb = arrays.rgb[pts]
        if unseen is not None:
            rgb = torch.where(unseen[front, None], torch.tensor(unseen_rgb, dtype=rgb.dtype, device=self.device), rgb)
        cols = [z[front, None], rgb, qu[front, None], qv[front, None]]
        if spacing is not None:
            cols.append(spacing[front, None])
        src = torch.cat(cols, dim=1)
        out = torch.zeros((n, src.shape[1]), dtype=torch.float32, device=self.device)
        out.index_add_(0, lq, src)
        cnt = torch.bincount(lq, minlength=n).to(torch.float32)
        s_sp = None if spacing is None else out[:, 6]
        return cnt, out[:, 0], [out[:, 1], out[:, 2], out[:, 3]], out[:, 4], out[:, 5], s_sp

    def floor_int(self, x):
        return self.torch.floor(x).to(self.torch.int64)

    def rint(self, x):
        return self.torch.round(x)

    def exp(self, x):
        return self.torch.exp(x)

    def minimum(self, a, b):
        return self.torch.minimum(a, b)

    def where(self, c, a, b):
        torch = self.torch
        if not isinstance(a, torch.Tensor):
            a = torch.as_tensor(a, dtype=b.dtype, device=self.device)
        if not isinstance(b, torch.Tensor):
            b = torch.as_tensor(b, dtype=a.dtype, device=self.device)
        return torch.where(c, a, b)

    def cat(self, parts):
        return self.torch.cat(parts)

    def stack(self, parts):
        return self.torch.stack(list(parts))

    def clamp(self, x, lo, hi):
        return x.clamp(lo, hi)

    def to_int64(self, x):
        return x.to(self.torch.int64)

    def as_f32(self, mask):
        return mask.to(self.torch.float32)

    def floor(self, x):
        return self.torch.floor(x)

    def sqrt(self, x):
        return self.torch.sqrt(x)

    def abs(self, x):
        return self.torch.abs(x)

    def maximum(self, a, b):
        return self.torch.maximum(a, b)

    def max_value(self, x) -> float:
        return float(x.max())

    def any(self, x) -> bool:
        return bool(x.any())

    def full2(self, h: int, w: int, value: float):
        return self.torch.full((h, w), value, dtype=self.torch.float32, device=self.device)

    def pad_ring(self, a, value):
        return self.torch.nn.functional.pad(a[None, None], (1, 1, 1, 1), value=value)[0, 0]

    def pad2(self, a, top: int, bottom: int, left: int, right: int, value):
        if not (top or bottom or left or right):
            return a
        h, w = a.shape
        out = self.torch.full((top + h + bottom, left + w + right), value, dtype=a.dtype, device=self.device)
        out[top : top + h, left : left + w] = a
        return out

    def ceil(self, x):
        return self.torch.ceil(x)

    def erode(self, x, r: int):
        f = self.torch.nn.functional
        return -f.max_pool2d(-x[None, None], 2 * r + 1, 1, r)[0, 0]

    def erode_quadrant(self, x, m: int, sy: int, sx: int):
        f = self.torch.nn.functional
        # Pad by m on the window's side, then a min-pool of (m + 1) x (m + 1) with stride 1.
        padding = (m if sx < 0 else 0, 0 if sx < 0 else m, m if sy < 0 else 0, 0 if sy < 0 else m)
        xp = f.pad(-x[None, None], padding, value=-math.inf)
        return -f.max_pool2d(xp, m + 1, 1)[0, 0]

    def index_grid(self, h: int, w: int, axis: int):
        key = (h, w, axis)
        if key not in self._grids:
            self._grids[key] = self.asarray(_index_grid(h, w, axis))
        return self._grids[key]

    def nonzero2(self, mask):
        r, c = self.torch.nonzero(mask, as_tuple=True)
        return r, c

    def lookup(self, table: np.ndarray, index):
        return self.asarray(table)[index.to(self.torch.int64)]

    def unique_values(self, x) -> list[float]:
        return self.torch.unique(x).tolist()

    def children(self, a):
        h, w = a.shape
        return a.reshape(h // 2, 2, w // 2, 2).permute(1, 3, 0, 2).reshape(4, h // 2, w // 2)


    def cloud_arrays(self, index: IndexedCloud, cloud=None, tag=()) -> _CloudArrays:
        key = ("torch-arrays", str(self.device), *tag)
        if key not in index.cache:
            c = index.cloud if cloud is None else cloud
            xyz = self.asarray(c.xyz)
            index.cache[key] = _CloudArrays(
                xyz[:, 0].contiguous(),
                xyz[:, 1].contiguous(),
                xyz[:, 2].contiguous(),
                self.asarray(c.rgb.astype(np.float32)),
                None if c.labels is None else self.asarray(c.labels),
            )
        return index.cache[key]
