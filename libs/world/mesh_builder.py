"""Accumulates flat-shaded, labelled primitives (boxes, cylinders) into one triangle mesh.

Shading is baked into the vertex colours (a fixed sky light), so that a renderer that only
interpolates colours still shows the shape of things: walls facing different ways differ in tone.
"""

from __future__ import annotations

import numpy as np

_LIGHT = np.array([0.35, 0.55, 0.76])
_LIGHT = _LIGHT / np.linalg.norm(_LIGHT)

# Each box face as 4 corner indices into the 8 corners (bit 0: x, bit 1: y, bit 2: z), counter-
# clockwise seen from outside, so the triangles' normals point out of the box.
_BOX_FACES = np.array(
    [
        [0, 2, 3, 1],  # -z
        [4, 5, 7, 6],  # +z
        [0, 1, 5, 4],  # -y
        [2, 6, 7, 3],  # +y
        [0, 4, 6, 2],  # -x
        [1, 3, 7, 5],  # +x
    ]
)


def shade(color: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Per-face colour under an ambient + directional light; normals (F, 3), color (3,) -> (F, 3)."""
    lam = np.clip(normals @ _LIGHT, -1.0, 1.0)
    # Faces turned from the light still get ambient light; this keeps every face readable.
    k = 0.72 + 0.28 * lam
    return np.clip(np.asarray(color, dtype=np.float64)[None, :] * k[:, None], 0.0, 1.0)


class MeshBuilder:
    """Collects triangles with per-face colours and labels; label names get ids on first use."""

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._tris: list[np.ndarray] = []
        self._cols: list[np.ndarray] = []
        self._labs: list[np.ndarray] = []
        self._n = 0
        self.label_ids: dict[str, int] = {}

    def label(self, name: str) -> int:
        if name not in self.label_ids:
            self.label_ids[name] = len(self.label_ids)
        return self.label_ids[name]

    def _add_quads(self, quads: np.ndarray, color, label: str) -> None:
        """quads (Q, 4, 3), counter-clockwise seen from the side the normal points to."""
        q = len(quads)
        normals = np.cross(quads[:, 1] - quads[:, 0], quads[:, 2] - quads[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        cols = shade(np.asarray(color), normals)
        verts = quads.reshape(-1, 3)
        base = self._n + 4 * np.arange(q)[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=0)
        self._verts.append(verts)
        self._cols.append(np.repeat(cols, 4, axis=0))
        self._tris.append(tris)
        self._labs.append(np.full(len(tris), self.label(label), dtype=np.int32))
        self._n += len(verts)

    def _add_tris(self, tris: np.ndarray, color, label: str) -> None:
        """tris (N, 3, 3), counter-clockwise seen from the side the normal points to."""
        normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        cols = shade(np.asarray(color), normals)
        self._verts.append(tris.reshape(-1, 3))
        self._cols.append(np.repeat(cols, 3, axis=0))
        self._tris.append(self._n + np.arange(3 * len(tris)).reshape(-1, 3))
        self._labs.append(np.full(len(tris), self.label(label), dtype=np.int32))
        self._n += 3 * len(tris)

    def box(self, lo, hi, color, label: str) -> None:
        """An axis-aligned box between corners ``lo`` and ``hi`` (metres)."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if np.any(hi - lo <= 1e-6):
            return
        bits = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)], dtype=bool)
        corners = np.where(bits, hi, lo)
        self._add_quads(corners[_BOX_FACES], color, label)

    def cylinder(self, centre_xy, radius: float, z0: float, z1: float, color, label: str, segments: int = 16, radius_top: float | None = None) -> None:
        """A vertical (optionally tapered) cylinder with caps."""
        rt = radius if radius_top is None else radius_top
        a = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
        ring = np.stack([np.cos(a), np.sin(a)], axis=1)
        cx, cy = float(centre_xy[0]), float(centre_xy[1])
        bot = np.column_stack([cx + radius * ring[:, 0], cy + radius * ring[:, 1], np.full(segments, z0)])
        top = np.column_stack([cx + rt * ring[:, 0], cy + rt * ring[:, 1], np.full(segments, z1)])
        nxt = np.roll(np.arange(segments), -1)
        if rt > 0:
            self._add_quads(np.stack([bot, bot[nxt], top[nxt], top], axis=1), color, label)
        else:  # a cone: the quads' top edge collapses to the apex
            self._add_tris(np.stack([bot, bot[nxt], top], axis=1), color, label)
        # Caps as triangle fans; degenerate triangles would cost ray-casting time and show nothing.
        c_top = np.array([cx, cy, z1])
        c_bot = np.array([cx, cy, z0])
        if rt > 0:
            self._add_tris(np.stack([np.broadcast_to(c_top, top.shape), top, top[nxt]], axis=1), color, label)
        self._add_tris(np.stack([np.broadcast_to(c_bot, bot.shape), bot[nxt], bot], axis=1), color, label)

    def build(self):
        """(vertices (N,3), triangles (T,3), colours (N,3) float32, labels (T,), label_names)."""
        v = np.concatenate(self._verts)
        t = np.concatenate(self._tris).astype(np.int32)
        c = np.concatenate(self._cols).astype(np.float32)
        lab = np.concatenate(self._labs)
        names = {i: n for n, i in self.label_ids.items()}
        return v, t, c, lab, names
