"""The top-down spatial map (paper Section 4.3, after SpatialNav): an occupancy grid projected
from the cloud, drawn with the agent, its trajectory, the numbered candidate waypoints and the room
names, for a multimodal LLM to read.

Cells are classified by the height of their points above the agent's floor: points within the
floor band are walkable floor, points in the obstacle band (what a body would bump into) are
obstacles, and a cell with neither is unknown. The grid and its base image depend only on the map
and the floor, so they are cached on the :class:`IndexedCloud` per floor; a request only warps that
image and draws the overlays.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import Field

from services.renderer.core.errors import RendererError
from shared.cloud import EmptyCloudError
from shared.export import nav2
from shared.export.nav2 import OccupancyConfig, occupancy_from_cloud
from libs.pointrender.cloud import IndexedCloud
from shared.registry import BackendConfig
from shared.schemas import Candidate, CandidateKind, Pose

log = logging.getLogger(__name__)

UNKNOWN, FREE, OBSTACLE = 0, 1, 2
# The most of a spatial map's area its legend may cover; a smaller map is drawn without one.
_LEGEND_MAX_AREA = 0.25

_COLOURS = {  # RGB
    UNKNOWN: (120, 120, 120),
    FREE: (238, 238, 232),
    OBSTACLE: (35, 35, 35),
}
_AGENT = (220, 30, 30)
_TRAJ = (30, 90, 220)
_CAND = (255, 150, 0)
_BACKTRACK = (160, 60, 200)


class SpatialMapConfig(BackendConfig):
    """How the occupancy grid is built and drawn."""

    cell_m: float = Field(0.05, ge=0.01, le=1.0)  # the bounds of shared.export.nav2.OccupancyConfig
    floor_band_m: tuple[float, float] = (-0.15, 0.15)  # relative to the agent's floor z
    obstacle_band_m: tuple[float, float] = (0.20, 1.60)
    min_obstacle_points: int = Field(3, ge=1)
    min_floor_points: int = Field(1, ge=1)
    floor_key_m: float = Field(0.25, gt=0.0)  # floors closer than this share one cached grid
    margin_m: float = Field(0.5, ge=0.0, le=10.0)
    room_label_suffix: str = " floor"  # label names like "kitchen floor" name a room


@dataclass(frozen=True)
class OccupancyGrid:
    """Cells (row 0 = largest y, column 0 = smallest x) of UNKNOWN / FREE / OBSTACLE."""

    cells: np.ndarray  # uint8 (rows, cols)
    origin_xy_m: tuple[float, float]  # world (x_min, y_max) of the grid's top-left corner
    cell_m: float
    floor_z_m: float
    rooms: tuple[tuple[str, float, float], ...]  # (name, x, y) at the centroid of each room's floor

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) world -> (N, 2) integer (row, col); may fall outside the grid."""
        xy = np.atleast_2d(xy)
        col = np.floor((xy[:, 0] - self.origin_xy_m[0]) / self.cell_m)
        row = np.floor((self.origin_xy_m[1] - xy[:, 1]) / self.cell_m)
        return np.stack([row, col], axis=1).astype(np.int64)

    def grid_to_world_affine(self) -> np.ndarray:
        """2x3 affine from grid pixel coordinates (col, row) to world (x, y) of the cell centre."""
        x0, y1 = self.origin_xy_m
        c = self.cell_m
        return np.array([[c, 0.0, x0 + 0.5 * c], [0.0, -c, y1 - 0.5 * c]])


@dataclass
class SpatialMapImage:
    """The drawn map: ``image`` RGB uint8, ``metres_per_px``, and the 2x3 affine world (x, y) ->
    image pixel (col, row) that placed every overlay."""

    image: np.ndarray
    metres_per_px: float
    world_to_px: np.ndarray
    agent_up: bool


class SpatialMapper:
    """Builds occupancy grids from an :class:`IndexedCloud` and draws spatial maps."""

    def __init__(self, config: SpatialMapConfig | None = None):
        self.config = config or SpatialMapConfig()

    def grid(self, index: IndexedCloud, floor_z_m: float) -> OccupancyGrid:
        """The occupancy grid of the floor at ``floor_z_m`` (cached per map and floor)."""
        cfg = self.config
        key = ("spatial-grid", round(floor_z_m / cfg.floor_key_m), cfg.model_dump_json())
        if key not in index.cache:
            index.cache[key] = self._build_grid(index, floor_z_m)
        return index.cache[key]

    def _build_grid(self, index: IndexedCloud, floor_z: float) -> OccupancyGrid:
        # The same cloud-to-grid rule as the Nav2 export (one mechanism: the grid the policy sees is the
        # grid a user downloads); only the cell values and the corner the origin names differ.
        cfg = self.config
        cloud = index.cloud
        if len(cloud) == 0:
            raise EmptyCloudError("no points to map")
        occupancy = OccupancyConfig(**cfg.model_dump(include=set(OccupancyConfig.model_fields)))
        try:
            nav = occupancy_from_cloud(cloud.xyz, floor_z, occupancy)
        except ValueError as exc:  # a grid past max_cells: the cloud spans more than any building
            raise RendererError(f"spatial map: {exc}") from exc
        cells = np.full(nav.cells.shape, UNKNOWN, np.uint8)
        cells[nav.cells == nav2.FREE] = FREE
        cells[nav.cells == nav2.OCCUPIED] = OBSTACLE
        rows = cells.shape[0]
        top_left = (nav.origin_m[0], nav.origin_m[1] + rows * cfg.cell_m)
        dz = cloud.xyz[:, 2] - np.float32(floor_z)
        on_floor = (dz >= cfg.floor_band_m[0]) & (dz <= cfg.floor_band_m[1])
        rooms = self._rooms(index, on_floor)
        log.debug("occupancy grid %dx%d at floor z=%.2f: %d rooms", *cells.shape, floor_z, len(rooms))
        return OccupancyGrid(cells, top_left, cfg.cell_m, float(floor_z), rooms)

    def _rooms(self, index: IndexedCloud, on_floor: np.ndarray) -> tuple[tuple[str, float, float], ...]:
        cloud, suffix = index.cloud, self.config.room_label_suffix
        if cloud.labels is None:
            return ()
        out = []
        for label_id, name in sorted(cloud.label_names.items()):
            if not name.endswith(suffix):
                continue
            pts = on_floor & (cloud.labels == label_id)
            if pts.any():
                # The medoid-ish point nearest the centroid keeps an L-shaped room's name on its floor.
                xy = cloud.xyz[pts, :2]
                centre = xy.mean(axis=0)
                near = xy[np.argmin(((xy - centre) ** 2).sum(axis=1))]
                out.append((name[: -len(suffix)].strip(), float(near[0]), float(near[1])))
        return tuple(out)

    def draw(
        self,
        index: IndexedCloud,
        pose: Pose,
        trajectory_m: np.ndarray | None = None,
        candidates: Sequence[Candidate] = (),
        agent_up: bool = False,
        size_px: int = 512,
        radius_m: float | None = None,
        room_labels: Sequence[tuple[str, float, float]] | None = None,
    ) -> SpatialMapImage:
        """Draw the map around ``pose``.

        ``agent_up``: rotate so the agent's heading points up (else +y world is up, +x right).
        ``radius_m``: half-width of the area shown around the agent; None shows the whole floor.
        ``room_labels``: (name, x, y) of the rooms to name, e.g. the scene graph's instances ("bedroom 2");
        None names the cloud's room labels (one name per room type, the centre of all its floor points).
        Candidates are waypoints at the agent position plus ``(dx_m, dy_m)`` (world axes), labelled
        with their ``index``; a backtrack candidate with an offset is drawn in another colour.
        """
        grid = self.grid(index, float(pose.position_m[2]))
        agent = np.array(pose.position_m[:2], float)
        rows, cols = grid.cells.shape
        corners = np.array([[0, 0], [cols, 0], [0, rows], [cols, rows]], float)
        g2w = grid.grid_to_world_affine()
        corners_w = corners @ g2w[:, :2].T + g2w[:, 2] - 0.5 * grid.cell_m * np.array([1, -1])
        if radius_m is not None:
            centre, half = agent, float(radius_m)
        elif agent_up:
            centre, half = agent, float(np.max(np.linalg.norm(corners_w - agent, axis=1)))
        else:
            lo, hi = corners_w.min(axis=0), corners_w.max(axis=0)
            centre, half = (lo + hi) / 2.0, float(np.max(hi - lo) / 2.0)
        half = max(half, 1.0)
        mpp = 2.0 * half / size_px
        # World (x, y) -> pixel: rotate so the chosen direction points up, scale, centre.
        rot = (math.pi / 2.0 - pose.heading_rad) if agent_up else 0.0
        c, s = math.cos(rot), math.sin(rot)
        lin = np.array([[c, -s], [-s, -c]]) / mpp  # second row flips y: image rows grow downwards
        w2p = np.concatenate([lin, (np.array([size_px / 2.0, size_px / 2.0]) - lin @ centre)[:, None]], axis=1)
        g2p = np.concatenate([w2p[:, :2] @ g2w[:, :2], (w2p[:, :2] @ g2w[:, 2] + w2p[:, 2])[:, None]], axis=1)

        base = self._base_image(index, grid)
        img = cv2.warpAffine(
            base, g2p, (size_px, size_px), flags=cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT, borderValue=_COLOURS[UNKNOWN],
        )
        img = np.ascontiguousarray(img)
        to_px = lambda xy: np.rint(np.atleast_2d(xy) @ w2p[:, :2].T + w2p[:, 2]).astype(np.int32)  # noqa: E731
        scale = size_px / 512.0

        for name, x, y in (grid.rooms if room_labels is None else room_labels):
            _text(img, name.upper(), to_px((x, y))[0], 0.5 * scale, (20, 110, 40), centred=True)

        if trajectory_m is not None and len(trajectory_m) > 0:
            pts = to_px(np.asarray(trajectory_m, float)[:, :2])
            if len(pts) > 1:
                cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, _TRAJ, max(2, round(2 * scale)), cv2.LINE_AA)
            for p in pts:
                cv2.circle(img, tuple(int(v) for v in p), max(2, round(3 * scale)), _TRAJ, -1, cv2.LINE_AA)

        a = to_px(agent)[0]
        r_c = max(8, round(11 * scale))
        for cand in candidates:
            if cand.kind == CandidateKind.STOP or (cand.dx_m == 0.0 and cand.dy_m == 0.0):
                continue
            colour = _BACKTRACK if cand.kind == CandidateKind.BACKTRACK else _CAND
            p = to_px(agent + np.array([cand.dx_m, cand.dy_m]))[0]
            cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in p), colour, 1, cv2.LINE_AA)
            cv2.circle(img, tuple(int(v) for v in p), r_c, colour, -1, cv2.LINE_AA)
            cv2.circle(img, tuple(int(v) for v in p), r_c, (0, 0, 0), 1, cv2.LINE_AA)
            _text(img, str(cand.index), p, 0.5 * scale, (0, 0, 0), centred=True, outline=False)

        # The agent: a disc with an arrow along its heading.
        head = agent + 0.6 * np.array([math.cos(pose.heading_rad), math.sin(pose.heading_rad)])
        tip = to_px(head)[0]
        direction = (tip - a).astype(float)
        norm = float(np.linalg.norm(direction)) or 1.0
        tip = (a + direction / norm * max(norm, 22 * scale)).astype(np.int32)
        cv2.arrowedLine(img, tuple(int(v) for v in a), tuple(int(v) for v in tip), _AGENT,
                        max(2, round(3 * scale)), cv2.LINE_AA, tipLength=0.35)
        cv2.circle(img, tuple(int(v) for v in a), max(5, round(7 * scale)), _AGENT, -1, cv2.LINE_AA)
        cv2.circle(img, tuple(int(v) for v in a), max(5, round(7 * scale)), (255, 255, 255), 1, cv2.LINE_AA)

        self._scale_bar(img, mpp, scale)
        title = "top-down map, agent heading up" if agent_up else "top-down map, +y up, +x right"
        legend = [("free", _COLOURS[FREE]), ("obstacle", _COLOURS[OBSTACLE]), ("unknown", _COLOURS[UNKNOWN]),
                  ("agent", _AGENT), ("path", _TRAJ), ("candidate", _CAND)]
        self._legend(img, title, legend, scale)
        return SpatialMapImage(img, mpp, w2p, agent_up)

    def _base_image(self, index: IndexedCloud, grid: OccupancyGrid) -> np.ndarray:
        key = ("spatial-base", id(grid))
        if key not in index.cache:
            lut = np.array([_COLOURS[UNKNOWN], _COLOURS[FREE], _COLOURS[OBSTACLE]], np.uint8)
            # Obstacles are drawn one cell fatter: thin walls stay closed lines at any zoom.
            cells = grid.cells.copy()
            cells[cv2.dilate((grid.cells == OBSTACLE).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0] = OBSTACLE
            index.cache[key] = lut[cells]
        return index.cache[key]

    @staticmethod
    def _legend(img: np.ndarray, title: str, legend: list[tuple[str, tuple]], scale: float) -> None:
        """Title and colour key on an opaque white panel in the top-left corner: dark text on white
        reads on any map (text straight on the grey unknown cells did not), at a size that stays
        legible on a small map."""
        font, fs = cv2.FONT_HERSHEY_SIMPLEX, max(0.4, 0.45 * scale)
        (tw, th), _ = cv2.getTextSize(title, font, fs, 1)
        line = th + max(6, round(8 * scale))
        sw = th + 2  # swatch side
        pad = max(4, round(6 * scale))
        width = max(tw, sw + pad + max(cv2.getTextSize(n, font, fs, 1)[0][0] for n, _ in legend))
        x0, y0 = pad, pad
        x1, y1 = x0 + width + 2 * pad, y0 + pad + line * (1 + len(legend))
        if (x1 - x0) * (y1 - y0) > _LEGEND_MAX_AREA * img.shape[0] * img.shape[1]:
            return  # a thumbnail: a legible key would hide the map it explains
        cv2.rectangle(img, (x0, y0), (x1, y1), (255, 255, 255), -1)
        cv2.rectangle(img, (x0, y0), (x1, y1), (60, 60, 60), 1)
        y = y0 + pad + th
        cv2.putText(img, title, (x0 + pad, y), font, fs, (0, 0, 0), 1, cv2.LINE_AA)
        for name, colour in legend:
            y += line
            cv2.rectangle(img, (x0 + pad, y - sw + 1), (x0 + pad + sw, y + 1), colour, -1)
            cv2.rectangle(img, (x0 + pad, y - sw + 1), (x0 + pad + sw, y + 1), (0, 0, 0), 1)
            cv2.putText(img, name, (x0 + 2 * pad + sw, y), font, fs, (0, 0, 0), 1, cv2.LINE_AA)

    @staticmethod
    def _scale_bar(img: np.ndarray, mpp: float, scale: float) -> None:
        size = img.shape[1]
        target_m = 0.2 * size * mpp
        nice = max((v for v in (0.5, 1, 2, 5, 10, 20, 50) if v <= target_m), default=0.5)
        length = int(round(nice / mpp))
        x0, y0 = int(12 * scale), img.shape[0] - int(14 * scale)
        cv2.rectangle(img, (x0 - 4, y0 - int(20 * scale)), (x0 + length + int(40 * scale), y0 + 6), (255, 255, 255), -1)
        cv2.line(img, (x0, y0), (x0 + length, y0), (0, 0, 0), 2)
        for x in (x0, x0 + length):
            cv2.line(img, (x, y0 - 5), (x, y0 + 4), (0, 0, 0), 2)
        label = f"{nice:g} m"
        _text(img, label, (x0 + length + 5, y0 + 4), 0.45 * scale, (0, 0, 0), outline=False)


def _text(img, text, org, font_scale, colour, centred=False, outline=True) -> None:
    font = cv2.FONT_HERSHEY_SIMPLEX
    thick = 1
    (tw, th), _ = cv2.getTextSize(text, font, font_scale, thick)
    x, y = int(org[0]), int(org[1])
    if centred:
        x, y = x - tw // 2, y + th // 2
    if outline:
        # The halo is the same text at the same thickness, shifted around it: a thicker stroke
        # advances each glyph further, so a thick white copy drifted right of the text ("agentt").
        for dx, dy in ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)):
            cv2.putText(img, text, (x + dx, y + dy), font, font_scale, (255, 255, 255), thick, cv2.LINE_AA)
    cv2.putText(img, text, (x, y), font, font_scale, colour, thick, cv2.LINE_AA)
