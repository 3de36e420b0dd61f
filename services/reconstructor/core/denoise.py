"""Depth denoising of a frame whose sensor declares its noise (``Frame.depth_noise_rel``, issue 33).

A structured-light or stereo camera's range error (sigma = rel * depth^2) is drawn afresh for every
pixel. Fused as it comes, each frame's points scatter a wall over several 3 cm voxels in front of and
behind it: the map's wall is a slab, and its render speckles (the voxel centroid averages only what
falls into one voxel, never across the slab). Neighbouring pixels of a surface measure nearly the
same depth, so the frame itself can average them out before fusion:

* the reference depth of a pixel is the median of its valid 3x3 neighbours (holes do not vote), or
  its own depth where that lies more than ``edge_sigmas`` sigma from the median: a pixel on the
  minority side of a depth edge keeps to its own surface (a noise draw that far out is rarer than
  1 in 10^4 at 4 sigma, and a wider test than the mean's gate keeps a 3-sigma draw from becoming
  its own biased reference);
* the pixel takes the mean of the neighbours within ``gate_sigmas`` sigma of that reference: a range
  filter, so a depth edge (the door frame in front of the next room) is never blended across.

The mean of n samples of one plane is that plane's depth at the centre (a linear ramp averages to
its middle), so slanted floors stay where they are; n = 25 cuts sigma about five-fold. Holes stay
holes and no pixel is added. A frame that declares no noise (0: exact or unknown) is returned as it
is, so exact depth gives bit-identical maps.

Two paths with identical results (tests compare them): the array code (reference, and the fallback
without numba) and a compiled loop (``kernels``-style, via ``shared.jit``).
"""

from __future__ import annotations

import numpy as np

from shared.jit import AVAILABLE, insert_sorted, kernel


def denoise_depth(depth: np.ndarray, noise_rel: float, window_px: int = 5, gate_sigmas: float = 2.5,
                  edge_sigmas: float = 4.0, compiled: bool | None = None) -> np.ndarray:
    """``depth`` (float32 (H, W), 0 or NaN = no measurement) with its declared noise averaged out.

    Returns the input itself when ``noise_rel`` <= 0 or ``window_px`` <= 1; ``compiled`` None: the
    compiled loop when numba is installed."""
    if not (noise_rel > 0.0) or window_px <= 1:
        return depth
    if window_px % 2 == 0:
        raise ValueError(f"window_px must be odd, got {window_px}")
    d = np.ascontiguousarray(depth, np.float32)
    use = AVAILABLE if compiled is None else compiled
    if use:
        if not AVAILABLE:
            raise RuntimeError("numba is not installed")
        out = np.empty_like(d)
        _denoise_kernel(d, np.float32(noise_rel), window_px // 2, np.float32(gate_sigmas),
                        np.float32(edge_sigmas), out)
        return out
    return _denoise_array(d, np.float32(noise_rel), window_px // 2, np.float32(gate_sigmas),
                          np.float32(edge_sigmas))


def _denoise_array(d: np.ndarray, rel: np.float32, r: int, g: np.float32, e: np.float32) -> np.ndarray:
    """The reference: every pixel's (2r+1)^2 window and 3x3 neighbourhood as stacked views, holes as inf."""
    h, w = d.shape
    k = 2 * r + 1
    valid = np.isfinite(d) & (d > 0)
    pad = np.pad(np.where(valid, d, np.inf).astype(np.float32), r, constant_values=np.inf)
    win = np.lib.stride_tricks.sliding_window_view(pad, (k, k)).reshape(h, w, k * k)
    near = np.lib.stride_tricks.sliding_window_view(pad[r - 1 : pad.shape[0] - r + 1, r - 1 : pad.shape[1] - r + 1],
                                                    (3, 3)).reshape(h, w, 9)
    srt = np.sort(near, axis=-1)
    n = np.isfinite(srt).sum(axis=-1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    med = np.float32(0.5) * (lo + hi)
    dc = np.where(valid, d, np.float32(0.0))
    ref = np.where(np.abs(dc - med) <= e * rel * med * med, med, dc)
    gate = g * rel * ref * ref
    sel = np.isfinite(win) & (np.abs(win - ref[..., None]) <= gate[..., None])
    # Summed in window order (row by row), as the compiled loop sums them.
    total = np.zeros((h, w), np.float32)
    cnt = np.zeros((h, w), np.int64)
    for q in range(k * k):
        s = sel[..., q]
        total = np.where(s, total + win[..., q], total)
        cnt += s
    out = np.where(valid & (cnt > 0), total / np.maximum(cnt, 1).astype(np.float32), d)
    return np.where(valid, out, d).astype(np.float32)


def _denoise_loop(d, rel, r, g, e, out):  # pragma: no cover - compiled; the array twin is the reference
    h, w = d.shape
    buf = np.empty(9, np.float32)
    for i in range(h):
        for j in range(w):
            c = d[i, j]
            if not (c > 0 and np.isfinite(c)):
                out[i, j] = c
                continue
            n = np.int64(0)  # not the literal 0, for which numba would compile insert_sorted again
            for a in range(i - 1, i + 2):
                for b in range(j - 1, j + 2):
                    if 0 <= a < h and 0 <= b < w:
                        v = d[a, b]
                        if v > 0 and np.isfinite(v):
                            n = insert_sorted(buf, n, v)  # the valid neighbours, ascending
            med = np.float32(0.5) * (buf[(n - 1) // 2] + buf[n // 2])
            ref = med if abs(c - med) <= e * rel * med * med else c
            gate = g * rel * ref * ref
            total = np.float32(0.0)
            cnt = 0
            for a in range(i - r, i + r + 1):
                for b in range(j - r, j + r + 1):
                    if 0 <= a < h and 0 <= b < w:
                        v = d[a, b]
                        if v > 0 and np.isfinite(v) and abs(v - ref) <= gate:
                            total = total + v
                            cnt += 1
            out[i, j] = total / np.float32(cnt) if cnt > 0 else c


_denoise_kernel = kernel()(_denoise_loop) if AVAILABLE else None
