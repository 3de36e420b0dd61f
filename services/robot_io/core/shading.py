"""Per-pixel lookups after the ray cast (depth of misses, colour, labels): one fused pass.

After Embree has found the triangle and barycentric coordinates of every ray, each pixel needs a
handful of table lookups. numpy does them as separate whole-image passes with temporaries (a
barycentric blend over 0.8 M pixels alone is ~15 ms); the compiled kernel below does all of them
in one loop over pixels (split across a few threads; it releases the GIL) and gives the same bytes (float32 arithmetic in the same order,
no fused multiply-add, truncation to uint8 like ``astype``). numba is optional: without it,
:func:`shade` runs the numpy version, which the tests compare against the kernel bit for bit.

Tables (row ``T`` is the "miss" row that clamped primitive ids index):

* ``tri_rgb`` (T+1, 3) uint8 - flat colour of each triangle;
* ``blend`` (T+1, 3, 3) float32 - [c0 + 0.5, c1 - c0, c2 - c0] in 0..255 units, or an empty array
  when the mesh is flat-coloured;
* ``tex_uvs`` (T+1, 3, 2) float32, ``tex_mids`` (T+1,) int32 (-1: vertex colour) and the texture
  images packed into one flat uint8 buffer with per-material ``tex_off`` / ``tex_w`` / ``tex_h``.
"""

from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

from shared.jit import AVAILABLE, kernel


@dataclass
class ShadingTables:
    """Per-triangle lookup tables of a scene (see the module docstring)."""

    miss_row: int
    tri_rgb: np.ndarray
    labels: np.ndarray
    blend: np.ndarray
    tex_uvs: np.ndarray
    tex_mids: np.ndarray
    tex_data: np.ndarray
    tex_off: np.ndarray
    tex_w: np.ndarray
    tex_h: np.ndarray

    @property
    def blended(self) -> bool:
        return self.blend.shape[0] > 0

    @property
    def textured(self) -> bool:
        return self.tex_mids.shape[0] > 0

    @classmethod
    def build(cls, vertex_colors: np.ndarray, triangles: np.ndarray, labels: np.ndarray, texture=None) -> ShadingTables:
        n = len(triangles)
        tri_cols = np.clip(vertex_colors[triangles], 0.0, 1.0)  # (T, 3 corners, 3)
        flat = bool(np.all(np.abs(tri_cols - tri_cols[:, :1]).max(axis=(1, 2)) < 1.0 / 512))
        tri_rgb = np.zeros((n + 1, 3), np.uint8)
        tri_rgb[:n] = np.round(tri_cols[:, 0] * 255)
        blend = np.zeros((0, 3, 3), np.float32)
        if not flat:
            # A convex combination of corner colours in 0..255: +0.5 then truncation rounds it
            # into uint8 range without a clip pass.
            c = (tri_cols * 255.0).astype(np.float32)
            blend = np.zeros((n + 1, 3, 3), np.float32)
            blend[:n, 0] = c[:, 0] + np.float32(0.5)
            blend[:n, 1] = c[:, 1] - c[:, 0]
            blend[:n, 2] = c[:, 2] - c[:, 0]
        lab = np.append(np.asarray(labels, dtype=np.int32), np.int32(-1))
        tex_uvs = np.zeros((0, 3, 2), np.float32)
        tex_mids = np.zeros(0, np.int32)
        tex_data = np.zeros(0, np.uint8)
        tex_off = np.zeros(0, np.int64)
        tex_w = np.zeros(0, np.int64)
        tex_h = np.zeros(0, np.int64)
        if texture is not None:
            tex_uvs = np.concatenate([texture.triangle_uvs.astype(np.float32).reshape(-1, 3, 2), np.zeros((1, 3, 2), np.float32)])
            tex_mids = np.append(np.asarray(texture.material_ids, dtype=np.int32), np.int32(-1))
            imgs = [np.ascontiguousarray(im, dtype=np.uint8) for im in texture.images]
            sizes = np.array([im.size for im in imgs], dtype=np.int64)
            tex_off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
            tex_w = np.array([im.shape[1] for im in imgs], dtype=np.int64)
            tex_h = np.array([im.shape[0] for im in imgs], dtype=np.int64)
            tex_data = np.concatenate([im.ravel() for im in imgs]) if imgs else tex_data
        return cls(n, tri_rgb, lab, blend, tex_uvs, tex_mids, tex_data, tex_off, tex_w, tex_h)


def shade(tables: ShadingTables, prim: np.ndarray, uv: np.ndarray, depth: np.ndarray, with_semantic: bool, use_kernel: bool = True):
    """(rgb (..., 3) uint8, semantic (...) int32 or None); zeroes ``depth`` at misses in place.

    ``prim`` (uint32, Embree's ids, 0xFFFFFFFF = miss) is clamped to the miss row in place.
    """
    shape = prim.shape
    if use_kernel and AVAILABLE:
        p = prim.reshape(-1)
        rgb = np.empty((p.shape[0], 3), np.uint8)
        sem = np.empty(p.shape[0] if with_semantic else 0, np.int32)
        args = (
            p, uv.reshape(-1, 2), depth.reshape(-1), tables.miss_row, tables.tri_rgb, tables.labels, tables.blend,
            tables.tex_uvs, tables.tex_mids, tables.tex_data, tables.tex_off, tables.tex_w, tables.tex_h, rgb, sem,
        )
        _run_kernel(args, p.shape[0])
        return rgb.reshape(*shape, 3), (sem.reshape(shape) if with_semantic else None)
    return _shade_numpy(tables, prim, uv, depth, with_semantic)


def _shade_numpy(t: ShadingTables, prim: np.ndarray, uv: np.ndarray, depth: np.ndarray, with_semantic: bool):
    np.minimum(prim, np.uint32(t.miss_row), out=prim)
    miss = np.isinf(depth)
    has_miss = bool(miss.any())
    if has_miss:
        depth[miss] = 0.0
    if t.blended:
        # Channels-first keeps every arithmetic pass contiguous: rows of 3 are slow in numpy.
        c = np.take(t.blend.reshape(-1, 9).T, prim.reshape(-1), axis=1)  # (9, N)
        w1 = np.ascontiguousarray(uv[..., 0]).reshape(-1)
        w2 = np.ascontiguousarray(uv[..., 1]).reshape(-1)
        acc = c[0:3]
        acc += w1 * c[3:6]
        acc += w2 * c[6:9]
        rgb = np.empty((*prim.shape, 3), np.uint8)
        rgb.reshape(-1, 3)[...] = acc.T
    else:
        rgb = np.take(t.tri_rgb, prim, axis=0)
    if t.textured:
        w1, w2 = uv[..., 0:1], uv[..., 1:2]
        mids = np.take(t.tex_mids, prim)
        sel = mids >= 0
        if sel.any():
            tuv = np.take(t.tex_uvs, prim[sel], axis=0)  # (S, 3, 2)
            a, b = w1[sel], w2[sel]
            st = tuv[:, 0] + a * (tuv[:, 1] - tuv[:, 0]) + b * (tuv[:, 2] - tuv[:, 0])
            m = mids[sel]
            iw, ih = t.tex_w[m], t.tex_h[m]
            # Repeat-wrap like GL_REPEAT; glTF/OBJ v runs upwards, image rows downwards.
            fu = st[:, 0] - np.floor(st[:, 0])
            fv = st[:, 1] - np.floor(st[:, 1])
            px = np.clip(np.floor(fu * iw).astype(np.int64), 0, iw - 1)
            py = np.clip(np.floor((np.float32(1.0) - fv) * ih).astype(np.int64), 0, ih - 1)
            base = t.tex_off[m] + (py * iw + px) * 3
            rgb[sel] = t.tex_data[base[:, None] + np.arange(3)]
    if has_miss:
        rgb[miss] = 0
    sem = np.take(t.labels, prim) if with_semantic else None
    return rgb, sem


def _shade_kernel(lo, hi, prim, uv, depth, miss_row, tri_rgb, labels, blend, tex_uvs, tex_mids, tex_data, tex_off, tex_w, tex_h, rgb, sem):  # pragma: no cover - compiled
    blended = blend.shape[0] > 0
    textured = tex_mids.shape[0] > 0
    with_sem = sem.shape[0] > 0
    one = np.float32(1.0)
    for i in range(lo, hi):
        p = prim[i]
        if p >= miss_row:
            p = miss_row
            prim[i] = p
            depth[i] = np.float32(0.0)
            rgb[i, 0] = 0
            rgb[i, 1] = 0
            rgb[i, 2] = 0
            if with_sem:
                sem[i] = labels[p]
            continue
        w1 = uv[i, 0]
        w2 = uv[i, 1]
        done = False
        if textured:
            m = tex_mids[p]
            if m >= 0:
                s = tex_uvs[p, 0, 0] + w1 * (tex_uvs[p, 1, 0] - tex_uvs[p, 0, 0]) + w2 * (tex_uvs[p, 2, 0] - tex_uvs[p, 0, 0])
                t = tex_uvs[p, 0, 1] + w1 * (tex_uvs[p, 1, 1] - tex_uvs[p, 0, 1]) + w2 * (tex_uvs[p, 2, 1] - tex_uvs[p, 0, 1])
                fu = s - np.floor(s)
                fv = t - np.floor(t)
                iw = tex_w[m]
                ih = tex_h[m]
                px = min(max(np.int64(np.floor(fu * iw)), 0), iw - 1)
                py = min(max(np.int64(np.floor((one - fv) * ih)), 0), ih - 1)
                base = tex_off[m] + (py * iw + px) * 3
                rgb[i, 0] = tex_data[base]
                rgb[i, 1] = tex_data[base + 1]
                rgb[i, 2] = tex_data[base + 2]
                done = True
        if not done:
            if blended:
                for ch in range(3):
                    acc = blend[p, 0, ch]
                    acc = acc + w1 * blend[p, 1, ch]
                    acc = acc + w2 * blend[p, 2, ch]
                    rgb[i, ch] = np.uint8(acc)
            else:
                rgb[i, 0] = tri_rgb[p, 0]
                rgb[i, 1] = tri_rgb[p, 1]
                rgb[i, 2] = tri_rgb[p, 2]
        if with_sem:
            sem[i] = labels[p]


_compiled = None


def _kernel():
    global _compiled
    if _compiled is None:
        _compiled = kernel(error_model="numpy")(_shade_kernel)
    return _compiled


def _run_kernel(args: tuple, n: int) -> None:
    """Run the kernel over ``n`` pixels in chunks on a small thread pool (the kernel drops the GIL).

    Plain threads rather than numba's ``parallel=True``: its default "workqueue" layer aborts the
    process when two threads enter parallel code at once, and a robot may render from several.
    """
    kernel = _kernel()
    workers = _workers()
    if n < 65536 or workers == 1:
        kernel(0, n, *args)
        return
    bounds = np.linspace(0, n, workers + 1).astype(np.int64)
    futures = [_pool().submit(kernel, int(a), int(b), *args) for a, b in zip(bounds[:-2], bounds[1:-1])]
    kernel(int(bounds[-2]), n, *args)
    for f in futures:
        f.result()


_pool_instance: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _workers() -> int:
    return max(1, min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)))


def _pool() -> ThreadPoolExecutor:
    global _pool_instance
    with _pool_lock:
        if _pool_instance is None:
            # Daemon-like helpers: the pool lives as long as the process; the caller does a share too.
            _pool_instance = ThreadPoolExecutor(max_workers=max(1, _workers() - 1), thread_name_prefix="robot-io-shade")
        return _pool_instance
