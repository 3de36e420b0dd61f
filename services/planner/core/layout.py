"""Image layouts of the step prompt: ``separate`` images, or ``mosaic`` composites of numbered tiles.

Local VLM servers cap the images of one request (vLLM's ``--limit-mm-per-prompt`` defaults to 1 image)
and OpenAI bills every image at least one 512 px tile: a 256 px view costs 255 tokens though it fills a
quarter of its tile. A mosaic packs the views of one kind into a single composite (SpatialNav's compass
image): the candidates as numbered cells, observed view above anticipated, and the history frames as
numbered tiles, so four 256 px views share one billed tile and a request carries three images at most.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

Layout = Literal["auto", "separate", "mosaic"]
LAYOUTS: tuple[str, ...] = ("auto", "separate", "mosaic")

# Cells per mosaic row: four 256 px cells make a 1024 px row, which OpenAI's rule scales to 768 px and
# bills as whole tiles; wider rows would be scaled down harder and lose detail.
MOSAIC_COLUMNS = 4
_BLANK = 0  # black: the same colour as an unreconstructed area, which the system prompt explains


@dataclass(frozen=True)
class Tile:
    """One cell of a mosaic: its number (drawn in its corner) and its images, top to bottom."""

    label: str
    images: tuple[np.ndarray | None, ...]


def fit(rgb: np.ndarray, px: int) -> np.ndarray:
    """``rgb`` resized to ``px`` x ``px`` (area interpolation when shrinking)."""
    if rgb.shape[:2] == (px, px):
        return rgb
    interp = cv2.INTER_AREA if max(rgb.shape[:2]) > px else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(rgb), (px, px), interpolation=interp)


def cap_side(rgb: np.ndarray, max_px: int | None) -> np.ndarray:
    """``rgb`` scaled down so that its longer side is at most ``max_px`` (unchanged when it fits)."""
    if max_px is None or max(rgb.shape[:2]) <= max_px:
        return rgb
    s = max_px / max(rgb.shape[:2])
    w, h = max(1, round(rgb.shape[1] * s)), max(1, round(rgb.shape[0] * s))
    return cv2.resize(np.ascontiguousarray(rgb), (w, h), interpolation=cv2.INTER_AREA)


def _label(img: np.ndarray, text: str) -> None:
    # A filled box under the number keeps it readable on any view (white walls, black holes).
    scale = max(0.4, img.shape[0] / 256 * 0.9)
    thick = max(1, round(scale * 2))
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    cv2.rectangle(img, (0, 0), (tw + 6, th + base + 6), (0, 0, 0), -1)
    cv2.putText(img, text, (3, th + 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 0), thick, cv2.LINE_AA)


def mosaic(tiles: list[Tile], tile_px: int, columns: int = MOSAIC_COLUMNS, line_px: int = 2) -> np.ndarray:
    """Cells in rows of ``columns``; each cell stacks its images (``None``: a black tile) and shows its
    label in the top-left corner. White lines over the cell borders separate the cells: drawn over, not
    added, so that a row of four 256 px cells stays 1024 px (an added gap would push it over a tile
    boundary and cost a third billed tile column)."""
    if not tiles:
        raise ValueError("a mosaic needs at least one tile")
    rows_per_cell = max(len(t.images) for t in tiles)
    cols = min(columns, len(tiles))
    n_rows = math.ceil(len(tiles) / cols)
    cell_w, cell_h = tile_px, tile_px * rows_per_cell
    canvas = np.full((n_rows * cell_h, cols * cell_w, 3), 255, np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, cols)
        y0, x0 = r * cell_h, c * cell_w
        for j in range(rows_per_cell):
            img = tile.images[j] if j < len(tile.images) else None
            part = np.full((tile_px, tile_px, 3), _BLANK, np.uint8) if img is None else fit(np.asarray(img), tile_px)
            canvas[y0 + j * tile_px : y0 + (j + 1) * tile_px, x0 : x0 + tile_px] = part
        cell = canvas[y0 : y0 + cell_h, x0 : x0 + cell_w]
        cell[:, -line_px:] = 255
        cell[-line_px:, :] = 255
        _label(cell, tile.label)
    return canvas


def best_columns(n_cells: int, cell_w: int, cell_h: int, cost, max_columns: int = 6) -> int:
    """The columns (1..``max_columns``) whose canvas costs the fewest image tokens by ``cost(w, h)``
    (the server's rule); ties go to the column count nearest :data:`MOSAIC_COLUMNS` (a squarer image)."""
    best = None
    for cols in range(1, min(n_cells, max_columns) + 1):
        rows = math.ceil(n_cells / cols)
        key = (cost(cols * cell_w, rows * cell_h), abs(cols - MOSAIC_COLUMNS), cols)
        best = key if best is None or key < best else best
    return best[2]


def stack(images: list[np.ndarray], gap_px: int = 8) -> np.ndarray:
    """Images one above the other on a white canvas (left-aligned): the single-image panel for servers
    that take one image per request."""
    width = max(i.shape[1] for i in images)
    height = sum(i.shape[0] for i in images) + gap_px * (len(images) - 1)
    canvas = np.full((height, width, 3), 255, np.uint8)
    y = 0
    for img in images:
        canvas[y : y + img.shape[0], : img.shape[1]] = img
        y += img.shape[0] + gap_px
    return canvas
