"""Pictures of any scene: a labelled top view per floor and a panorama contact sheet.

    python -m services.robot_io.tools.pictures --scene generated:0 --out pictures/
    python -m services.robot_io.tools.pictures --scene generated:1:floors=2 --out pictures/
    python -m services.robot_io.tools.pictures --scene ../shared/data/replica_office0/office0_mesh.ply --out pictures/
    python -m services.robot_io.tools.pictures --scene ../shared/data/habitat_test_assets/chair.glb --out pictures/

The two pictures show at a glance whether a scene file loaded the right way up (floors seen from
above, walls vertical in the panorama) and in its colours (textures, material colours). A scene
with no floor to stand on (a single object) is looked at from outside: the panorama's first view
faces it.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from libs.world.errors import NoWalkableAreaError  # noqa: E402
from services.robot_io.core.render import RenderOutput, SceneRenderer  # noqa: E402
from services.robot_io.core.robot import SimConfig, SimRobot  # noqa: E402
from libs.world.scene import Scene, load_scene  # noqa: E402
from shared.geometry import panorama_headings  # noqa: E402

log = logging.getLogger(__name__)


def top_view(renderer: SceneRenderer, floor_z_m: float | None, px_per_m: float = 40.0) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Orthographic colour image seen from just under the ceiling of the storey at ``floor_z_m``
    (from above the whole scene when None), in the simulator's own colours (textures included)."""
    lo, hi = renderer.scene.bounds_m
    extent = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]), 1e-3)
    px_per_m = min(max(px_per_m, 400.0 / extent), 1600.0 / extent)  # small objects get pixels too
    w = max(1, int(math.ceil((hi[0] - lo[0]) * px_per_m)))
    h = max(1, int(math.ceil((hi[1] - lo[1]) * px_per_m)))
    xs = lo[0] + (np.arange(w) + 0.5) / px_per_m
    ys = hi[1] - (np.arange(h) + 0.5) / px_per_m  # image rows go south
    xx, yy = np.meshgrid(xs, ys)
    # Start below the ceiling so the walls show in section and the rooms are open to view.
    top = float(hi[2]) + 0.1 if floor_z_m is None else floor_z_m + 2.3
    base = float(lo[2]) if floor_z_m is None else floor_z_m
    origins = np.stack([xx, yy, np.full_like(xx, top)], axis=-1)
    dirs = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
    t, rgb8, _ = renderer.cast_shaded(origins, dirs)
    rgb = rgb8.astype(np.float32) / 255.0
    # Shade by height so furniture stands out from the floor.
    z = top - np.where(np.isfinite(t), t, 0.0)
    span = max(1.5, top - base)
    rgb *= np.clip(0.75 + 0.25 * (z - base) / span, 0.6, 1.1)[..., None]
    rgb[~np.isfinite(t)] = 1.0
    return np.clip(rgb, 0, 1), (lo[0], hi[0], lo[1], hi[1])


def draw_top_views(scene: Scene, renderer: SceneRenderer, robot: SimRobot | None, out: Path) -> list[Path]:
    floors = sorted({r.floor for r in scene.rooms}) or [0]
    paths = []
    for fl in floors:
        if robot is not None:
            fz = next((r.floor_z_m for r in scene.rooms if r.floor == fl), float(robot.true_pose.position_m[2]))
        else:
            fz = None
        img, extent = top_view(renderer, fz)
        fig, ax = plt.subplots(figsize=(10, 10 * img.shape[0] / max(img.shape[1], 1) + 0.5), dpi=120)
        ax.imshow(img, extent=extent, origin="upper")
        if robot is not None:
            nodes = robot.nav.nodes_m
            sel = (robot.nav.component == robot.nav.main_component) & (np.abs(nodes[:, 2] - fz) < 1.4)
            ax.scatter(nodes[sel, 0], nodes[sel, 1], s=0.05, c="#2a9d8f", alpha=0.25, linewidths=0, label="walkable (main region)")
        for r in scene.rooms:
            if r.floor != fl:
                continue
            c = r.centre_m
            ax.text(c[0], c[1], f"{r.name}\n{r.area_m2:.0f} m²", ha="center", va="center", fontsize=9, weight="bold",
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", alpha=0.75, lw=0))
        for o in scene.objects:
            if (fz is None or abs(o.position_m[2] - fz) < 0.5) and o.label in LANDMARKS:
                ax.text(o.position_m[0], o.position_m[1], o.label, fontsize=6, ha="center", va="center", color="black")
        if robot is not None:
            p = robot.true_pose
            if abs(p.position_m[2] - fz) < 1.0:
                ax.arrow(p.position_m[0], p.position_m[1], 0.6 * math.cos(p.heading_rad), 0.6 * math.sin(p.heading_rad),
                         width=0.08, color="red", length_includes_head=True)
            ax.set_title(f"{scene.name} - floor {fl} ({robot.nav.reachable_area_m2:.0f} m² reachable)")
        else:
            ax.set_title(f"{scene.name} - seen from above (no floor to stand on)")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        fig.tight_layout()
        path = out / f"top_view_floor{fl}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths


MIN_ROOM_M2 = 2.0  # less walkable floor than this is an object, not a place
LANDMARKS = ("bed", "sofa", "fridge", "toilet", "plant", "tv", "bathtub", "desk", "stove", "wardrobe", "bookshelf",
             "table", "chair", "couch", "sink", "cabinet")


def object_panorama(renderer: SceneRenderer, views: int, size_px: int) -> tuple[RenderOutput, np.ndarray]:
    """Views from a point outside a scene without floor, at the height of its middle; view 0 faces it."""
    from shared.geometry import PinholeCamera

    lo, hi = renderer.scene.bounds_m
    centre = (lo + hi) / 2
    dist = 0.8 * float(np.linalg.norm(hi - lo)) + 0.3
    feet = np.array([centre[0] - dist, centre[1], lo[2]])
    headings = panorama_headings(0.0, views)
    out = renderer.render_views(feet, headings, PinholeCamera(size_px, size_px, 90.0), 0.0, float(centre[2] - lo[2]))
    return out, headings


def contact_sheet(pano: RenderOutput, headings_rad: np.ndarray, out: Path) -> Path:
    v, h, w = pano.depth_m.shape
    depth = pano.depth_m
    dmax = max(float(np.percentile(depth[depth > 0], 99)) if (depth > 0).any() else 1.0, 1e-3)
    d8 = np.clip(depth / dmax * 255, 0, 255).astype(np.uint8).reshape(v * h, w)
    dcol = cv2.applyColorMap(d8, cv2.COLORMAP_TURBO)[..., ::-1].reshape(v, h, w, 3)
    dcol[depth == 0] = 0
    rows = [pano.rgb, dcol]
    if pano.semantic is not None and (pano.semantic >= 0).any():
        rng = np.random.default_rng(7)
        lut = rng.integers(40, 255, size=(int(pano.semantic.max()) + 2, 3)).astype(np.uint8)
        sem = lut[pano.semantic + 1]
        sem[pano.semantic < 0] = 0
        rows.append(sem)
    sheet = np.concatenate([np.concatenate(list(r), axis=1) for r in rows], axis=0).copy()
    for i, hd in enumerate(headings_rad):
        cv2.putText(sheet, f"{i}: {math.degrees(hd):.0f} deg", (i * w + 6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    path = out / "panorama.png"
    cv2.imwrite(str(path), sheet[..., ::-1])
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="generated:0", help="generated:<seed>[:floors=2] or a mesh file")
    ap.add_argument("--scenes-dir", default=None)
    ap.add_argument("--out", default="pictures", type=Path)
    ap.add_argument("--size", default=256, type=int, help="panorama view size in pixels")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = SimConfig(scene=args.scene, scenes_dir=args.scenes_dir, camera={"width_px": args.size, "height_px": args.size})
    scene = load_scene(cfg.scene, cfg.scenes_dir)
    try:
        robot: SimRobot | None = SimRobot(cfg, scene=scene)
    except NoWalkableAreaError:
        robot = None  # one object, no floor: look at it from outside
    if robot is not None and robot.nav.reachable_area_m2 < MIN_ROOM_M2:
        robot.close()
        robot = None  # the seat of a chair is no place to stand and look around
    if robot is not None:
        with robot:
            pano = robot.observe()
            paths = draw_top_views(scene, robot.renderer, robot, args.out)
            paths.append(contact_sheet(RenderOutput(pano.rgb, pano.depth_m, pano.semantic), pano.headings_rad, args.out))
    else:
        renderer = SceneRenderer(scene)
        pano_out, headings = object_panorama(renderer, cfg.views, args.size)
        paths = draw_top_views(scene, renderer, None, args.out) + [contact_sheet(pano_out, headings, args.out)]
    for p in paths:
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
