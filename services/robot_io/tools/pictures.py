"""Pictures of a scene: a labelled top view per floor and a panorama contact sheet.

    python -m services.robot_io.tools.pictures --scene generated:0 --out pictures/
    python -m services.robot_io.tools.pictures --scene generated:1:floors=2 --out pictures/
    python -m services.robot_io.tools.pictures --scene ../shared/data/replica_office0/office0_mesh.ply --out pictures/
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

from services.robot_io.core.robot import SimConfig, SimRobot  # noqa: E402

log = logging.getLogger(__name__)


def top_view(robot: SimRobot, floor_z_m: float, px_per_m: float = 40.0) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Orthographic colour image seen from just under the ceiling of the storey at ``floor_z_m``."""
    lo, hi = robot.scene.bounds_m
    w = int(math.ceil((hi[0] - lo[0]) * px_per_m))
    h = int(math.ceil((hi[1] - lo[1]) * px_per_m))
    xs = lo[0] + (np.arange(w) + 0.5) / px_per_m
    ys = hi[1] - (np.arange(h) + 0.5) / px_per_m  # image rows go south
    xx, yy = np.meshgrid(xs, ys)
    # Start below the ceiling so the walls show in section and the rooms are open to view.
    origins = np.stack([xx, yy, np.full_like(xx, floor_z_m + 2.3)], axis=-1)
    dirs = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
    hit = robot.renderer.cast(origins, dirs)
    prim = hit["primitive_ids"]
    miss = prim == np.uint32(0xFFFFFFFF)
    tri_rgb = robot.renderer.triangle_colors()
    rgb = np.zeros((h, w, 3), np.float32)
    rgb[~miss] = tri_rgb[prim[~miss]]
    # Shade by height so furniture stands out from the floor.
    z = floor_z_m + 2.3 - hit["t_hit"]
    rgb *= np.clip(0.75 + 0.25 * (z - floor_z_m) / 1.5, 0.6, 1.1)[..., None]
    return np.clip(rgb, 0, 1), (lo[0], hi[0], lo[1], hi[1])


def draw_house(robot: SimRobot, out: Path) -> list[Path]:
    scene = robot.scene
    floors = sorted({r.floor for r in scene.rooms}) or [0]
    paths = []
    for fl in floors:
        fz = next((r.floor_z_m for r in scene.rooms if r.floor == fl), float(robot.true_pose.position_m[2]))
        img, extent = top_view(robot, fz)
        fig, ax = plt.subplots(figsize=(10, 10 * img.shape[0] / max(img.shape[1], 1) + 0.5), dpi=120)
        ax.imshow(img, extent=extent, origin="upper")
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
            if abs(o.position_m[2] - fz) < 0.5 and o.label in ("bed", "sofa", "fridge", "toilet", "plant", "tv", "bathtub", "desk", "stove", "wardrobe", "bookshelf"):
                ax.text(o.position_m[0], o.position_m[1], o.label, fontsize=6, ha="center", va="center", color="black")
        p = robot.true_pose
        if abs(p.position_m[2] - fz) < 1.0:
            ax.arrow(p.position_m[0], p.position_m[1], 0.6 * math.cos(p.heading_rad), 0.6 * math.sin(p.heading_rad),
                     width=0.08, color="red", length_includes_head=True)
        ax.set_title(f"{scene.name} - floor {fl} ({robot.nav.reachable_area_m2:.0f} m² reachable)")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        fig.tight_layout()
        path = out / f"top_view_floor{fl}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths


def contact_sheet(robot: SimRobot, out: Path) -> Path:
    pano = robot.observe()
    v, h, w = pano.depth_m.shape
    depth = pano.depth_m
    dmax = max(float(np.percentile(depth[depth > 0], 99)) if (depth > 0).any() else 1.0, 1e-3)
    d8 = np.clip(depth / dmax * 255, 0, 255).astype(np.uint8).reshape(v * h, w)
    dcol = cv2.applyColorMap(d8, cv2.COLORMAP_TURBO)[..., ::-1].reshape(v, h, w, 3)
    dcol[depth == 0] = 0
    rows = [pano.rgb, dcol]
    if pano.semantic is not None:
        rng = np.random.default_rng(7)
        lut = rng.integers(40, 255, size=(int(pano.semantic.max()) + 2, 3)).astype(np.uint8)
        sem = lut[pano.semantic + 1]
        sem[pano.semantic < 0] = 0
        rows.append(sem)
    sheet = np.concatenate([np.concatenate(list(r), axis=1) for r in rows], axis=0).copy()
    for i, hd in enumerate(pano.headings_rad):
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
    with SimRobot(cfg) as robot:
        paths = draw_house(robot, args.out) + [contact_sheet(robot, args.out)]
    for p in paths:
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
