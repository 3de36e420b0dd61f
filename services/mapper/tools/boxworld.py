"""A tiny box-room world and robot for testing the mapper without the robot-io simulator.

Walls are axis-aligned boxes on a floor; an optional straight staircase joins a second floor.
Panoramas are ray-cast with open3d's RaycastingScene using the conventions of
:mod:`shared.geometry`; motion follows a 2D walkability grid (walls inflated by the body radius)
whose floor height is looked up per cell, so the robot climbs the staircase like a ramp.
It is deliberately small: the real simulator lives in ``services/robot_io``.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from shared.geometry import PANORAMA_VIEWS, PinholeCamera, camera_pose, panorama_headings
from shared.o3d import o3d
from shared.schemas import CameraIntrinsics, Frame, MoveResult, MoveStatus, Panorama, Pose


@dataclass
class Box:
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


@dataclass
class BoxWorld:
    """Boxes (walls, furniture, steps) plus the floor slabs they stand on."""

    boxes: list[Box]
    floors: list[Box]  # walkable slabs; their top is the floor height
    cell_m: float = 0.05
    start: tuple[float, float, float] = (1.0, 1.0, 0.0)
    _scene: o3d.t.geometry.RaycastingScene | None = field(default=None, init=False, repr=False)

    def mesh(self) -> o3d.geometry.TriangleMesh:
        mesh = o3d.geometry.TriangleMesh()
        for b in [*self.boxes, *self.floors]:
            size = np.subtract(b.hi, b.lo)
            m = o3d.geometry.TriangleMesh.create_box(*np.maximum(size, 1e-3))
            m.translate(b.lo)
            mesh += m
        return mesh

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        if self._scene is None:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(self.mesh()))
        return self._scene

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        pts = np.array([[*b.lo] for b in self.floors] + [[*b.hi] for b in self.floors])
        return pts.min(axis=0), pts.max(axis=0)

    def floor_height(self, x: np.ndarray, y: np.ndarray, near_z: np.ndarray) -> np.ndarray:
        """Walkable height under (x, y) closest to ``near_z`` (NaN where there is no floor)."""
        x, y, near_z = np.broadcast_arrays(np.asarray(x), np.asarray(y), np.asarray(near_z))
        best = np.full(x.shape, np.nan)
        for f in self.floors:
            inside = (x >= f.lo[0]) & (x <= f.hi[0]) & (y >= f.lo[1]) & (y <= f.hi[1])
            top = f.hi[2]
            # A slab is reachable from near_z when it lies within a step of it.
            ok = inside & (np.abs(top - near_z) < 0.3)
            better = ok & (np.isnan(best) | (np.abs(top - near_z) < np.abs(best - near_z)))
            best = np.where(better, top, best)
        return best

    def blocked(self, x: float, y: float, z: float, radius_m: float) -> bool:
        """True when a disc of ``radius_m`` at (x, y) on floor z touches a wall box."""
        for b in self.boxes:
            if b.hi[2] <= z + 0.25 or b.lo[2] >= z + 1.6:
                continue  # steps and things above the head do not block the body
            dx = max(b.lo[0] - x, 0.0, x - b.hi[0])
            dy = max(b.lo[1] - y, 0.0, y - b.hi[1])
            if dx * dx + dy * dy < radius_m * radius_m:
                return True
        return False

    def reachable_cells(self, radius_m: float, cell_m: float = 0.1) -> np.ndarray:
        """(N, 3) centres of cells the robot can reach from the start (flood fill)."""
        lo, hi = self.bounds()
        xs = np.arange(lo[0] + cell_m / 2, hi[0], cell_m)
        ys = np.arange(lo[1] + cell_m / 2, hi[1], cell_m)
        out = []
        zs = sorted({f.hi[2] for f in self.floors})
        # Per floor height level a free mask, then one flood fill over the union (stairs joined
        # through their slabs, which have their own levels).
        levels = {}
        for z in zs:
            free = np.zeros((len(xs), len(ys)), dtype=bool)
            for i, x in enumerate(xs):
                for j, y in enumerate(ys):
                    h = self.floor_height(x, y, z)
                    free[i, j] = np.isfinite(h) and abs(h - z) < 1e-6 and not self.blocked(
                        x, y, z, radius_m
                    )
            levels[z] = free
        nodes = {}
        for z, free in levels.items():
            for i, j in zip(*np.nonzero(free), strict=True):
                nodes[(i, j, z)] = len(nodes)
        import networkx as nx

        g = nx.Graph()
        g.add_nodes_from(nodes)
        for i, j, z in nodes:
            for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
                for z2 in zs:
                    if (i + di, j + dj, z2) in nodes and abs(z2 - z) < 0.3:
                        g.add_edge((i, j, z), (i + di, j + dj, z2))
        sx, sy, sz = self.start
        si = int(np.argmin(np.abs(xs - sx)))
        sj = int(np.argmin(np.abs(ys - sy)))
        seeds = [n for n in g if n[0] == si and n[1] == sj and abs(n[2] - sz) < 0.3]
        if not seeds:
            return np.zeros((0, 3))
        comp = nx.node_connected_component(g, seeds[0])
        out = [(xs[i], ys[j], z) for i, j, z in comp]
        return np.array(out)


def rooms_world(with_stairs: bool = False) -> BoxWorld:
    """Three rooms (6 x 4, 4 x 4, 4 x 4 m) joined by doors; optionally stairs to an upper room."""
    t, h = 0.1, 2.6
    boxes = [
        # outer walls of a 10 x 8 m footprint
        Box((0, -t, 0), (10, 0, h)),
        Box((0, 8, 0), (10, 8 + t, h)),
        Box((-t, 0, 0), (0, 8, h)),
        Box((10, 0, 0), (10 + t, 8, h)),
        # wall y=4 splitting south (y<4) from north, door at x in [1.5, 2.5]
        Box((0, 4 - t / 2, 0), (1.5, 4 + t / 2, h)),
        Box((2.5, 4 - t / 2, 0), (10, 4 + t / 2, h)),
        # wall x=6 splitting the south half, door at y in [1.5, 2.5]
        Box((6 - t / 2, 0, 0), (6 + t / 2, 1.5, h)),
        Box((6 - t / 2, 2.5, 0), (6 + t / 2, 4, h)),
        # a table in the big room
        Box((3.0, 1.5, 0.7), (4.2, 2.3, 0.76)),
        Box((3.0, 1.5, 0.0), (3.06, 1.56, 0.7)),
        Box((4.14, 2.24, 0.0), (4.2, 2.3, 0.7)),
        Box((3.0, 2.24, 0.0), (3.06, 2.3, 0.7)),
        Box((4.14, 1.5, 0.0), (4.2, 1.56, 0.7)),
    ]
    floors = [Box((0, 0, -0.1), (10, 8, 0.0))]
    if with_stairs:
        # Straight staircase in the north room going +x from x=4 to x=8 at y in [6.5, 7.8],
        # 16 steps of 0.17 m onto an upper landing room (x 8..10, y 4..8) at z = 2.72.
        rise, run = 0.17, 0.25
        n = 16
        for k in range(n):
            x0 = 4.0 + k * run
            top = (k + 1) * rise
            floors.append(Box((x0, 6.5, top - 0.05), (x0 + run, 7.8, top)))
            boxes.append(Box((x0, 6.5, 0.0), (x0 + run, 7.8, top - 0.05)))
        z1 = n * rise
        floors[0] = Box((0, 0, -0.1), (10, 8, 0.0))
        floors.append(Box((8.0, 4.0 + t / 2, z1 - 0.1), (10, 8, z1)))
        boxes += [
            Box((8.0, 4.0, z1), (10, 4.0 + t, z1 + h)),  # upper room walls
            Box((10, 4.0, z1), (10 + t, 8, z1 + h)),
            Box((8.0, 8, z1), (10, 8 + t, z1 + h)),
            Box((8.0 - t, 4.0, z1), (8.0, 6.4, z1 + h)),
            Box((4.0, 6.4, 0.0), (8.0, 6.5, z1 + h)),  # stair side wall
        ]
        # The ground floor under the landing is a closed cupboard.
        boxes.append(Box((8.0, 4.0 + t / 2, 0.0), (10, 8, z1 - 0.1)))
    return BoxWorld(boxes=boxes, floors=floors)


class BoxWorldRobot:
    """A robot in a :class:`BoxWorld`: observe, move_to, turn, look_around, recording."""

    def __init__(
        self,
        world: BoxWorld,
        camera: PinholeCamera | None = None,
        body_radius_m: float = 0.2,
        step_m: float = 0.05,
    ):
        self.world = world
        self.camera = camera or PinholeCamera(64, 64, 90.0)
        self.body_radius_m = body_radius_m
        self.step_m = step_m
        self._pos = np.array(world.start, dtype=np.float64)
        self._heading = 0.0
        self._sink: Callable[[Frame], None] | None = None
        self._frames = 0
        self.moves = 0
        self.observations = 0

    @property
    def pose(self) -> Pose:
        return Pose(position_m=tuple(float(v) for v in self._pos), heading_rad=self._heading)

    def reset(self, pose: Pose | None = None) -> Pose:
        self._pos = np.array(pose.position_m if pose else self.world.start, dtype=np.float64)
        self._heading = pose.heading_rad if pose else 0.0
        return self.pose

    def _render(self, heading: float, pitch: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        cam = self.camera
        t = camera_pose(self._pos, heading, pitch)
        rays_cam = cam.pixel_rays().reshape(-1, 3)
        dirs = rays_cam @ t[:3, :3].T
        norms = np.linalg.norm(dirs, axis=1, keepdims=True)
        rays = np.concatenate([np.broadcast_to(t[:3, 3], dirs.shape), dirs / norms], axis=1)
        ans = self.world.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
        dist = ans["t_hit"].numpy()
        depth = np.where(np.isfinite(dist), dist / norms[:, 0], 0.0).astype(np.float32)
        depth = depth.reshape(cam.height_px, cam.width_px)
        shade = np.clip(depth * 40, 0, 255).astype(np.uint8)
        rgb = np.repeat(shade[..., None], 3, axis=2)
        return rgb, depth

    def observe(self) -> Panorama:
        self.observations += 1
        heads = panorama_headings(self._heading, PANORAMA_VIEWS)
        rgbs, depths = zip(*(self._render(float(h)) for h in heads), strict=True)
        cam = self.camera
        return Panorama(
            pose=self.pose,
            camera=CameraIntrinsics(
                width_px=cam.width_px, height_px=cam.height_px, hfov_deg=cam.hfov_deg
            ),
            headings_rad=np.asarray(heads, dtype=np.float64),
            rgb=np.stack(rgbs),
            depth_m=np.stack(depths),
        )

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult:
        self.moves += 1
        dist = math.hypot(dx_m, dy_m)
        n = max(1, int(math.ceil(dist / self.step_m)))
        start = self._pos.copy()
        status = MoveStatus.REACHED
        steps = 0
        if dist > 1e-9:
            self._heading = math.atan2(dy_m, dx_m)
        for k in range(1, n + 1):
            x = start[0] + dx_m * k / n
            y = start[1] + dy_m * k / n
            z = self.world.floor_height(x, y, self._pos[2])
            if not np.isfinite(z) or self.world.blocked(x, y, float(z), self.body_radius_m):
                status = MoveStatus.BLOCKED
                break
            self._pos = np.array([x, y, float(z)])
            steps += 1
            if self._sink is not None and k % 4 == 0:
                self._emit(0.0)
        travelled = float(np.linalg.norm(self._pos[:2] - start[:2]))
        return MoveResult(status=status, pose=self.pose, travelled_m=travelled, steps=steps)

    def turn(self, angle_rad: float) -> Pose:
        self._heading = float((self._heading + angle_rad + math.pi) % (2 * math.pi) - math.pi)
        if self._sink is not None:
            self._emit(0.0)
        return self.pose

    def look_around(self) -> list[Frame]:
        frames = []
        base = self._heading
        for yaw, pitch in ((0, 0), (60, 0), (-60, 0), (0, 45), (0, -45), (0, 0)):
            self._heading = base + math.radians(yaw)
            frames.append(self._emit(math.radians(pitch)))
        self._heading = base
        return frames

    def _emit(self, pitch: float) -> Frame:
        rgb, depth = self._render(self._heading, pitch)
        cam = self.camera
        frame = Frame(
            index=self._frames,
            timestamp_s=time.time(),
            pose=self.pose,
            pitch_rad=pitch,
            imu_heading_rad=self._heading,
            camera=CameraIntrinsics(
                width_px=cam.width_px, height_px=cam.height_px, hfov_deg=cam.hfov_deg
            ),
            rgb=rgb,
            depth_m=depth,
        )
        self._frames += 1
        if self._sink is not None:
            self._sink(frame)
        return frame

    @contextlib.contextmanager
    def recording(self, sink: Callable[[Frame], None], rate_hz: float = 5.0) -> Iterator[None]:
        self._sink = sink
        try:
            yield
        finally:
            self._sink = None
