"""Debug picture of a discovery: occupancy, graph coloured by region, hubs and tours, per floor.

    python -m tools.exploration_pictures --scene generated:0 --out DIR [--size 64]
    python -m tools.exploration_pictures --scene boxworld --out DIR
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from shared.geometry import PinholeCamera  # noqa: E402
from shared.schemas import CameraIntrinsics  # noqa: E402

from services.mapper.core import Discovery, NodeStatus, discover  # noqa: E402
from services.mapper.core.occupancy import FREE, OCCUPIED  # noqa: E402


def render(d: Discovery, out_png: Path) -> Path:
    """Write one PNG with a panel per floor; returns its path."""
    floors = d.scene.floors
    fig, axes = plt.subplots(1, max(1, len(floors)), figsize=(7 * max(1, len(floors)), 7), squeeze=False)
    cmap = plt.get_cmap("tab20")
    g = d.result.graph.g
    for ax, fl in zip(axes[0], floors, strict=False):
        occ = fl.occupancy
        img = np.full(occ.cells.shape, 0.75)
        img[occ.cells == FREE] = 1.0
        img[occ.cells == OCCUPIED] = 0.1
        ext = [occ.origin_m[0], occ.origin_m[0] + occ.cells.shape[0] * occ.cell_m,
               occ.origin_m[1], occ.origin_m[1] + occ.cells.shape[1] * occ.cell_m]
        ax.imshow(img.T, origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1)
        on_floor = {n for n, a in g.nodes(data=True) if a.get("floor") == fl.index}
        for u, v in g.edges:
            if u in on_floor or v in on_floor:
                p, q = g.nodes[u]["pos"], g.nodes[v]["pos"]
                ax.plot([p[0], q[0]], [p[1], q[1]], color="0.45", lw=0.8, zorder=2)
        for n in on_floor:
            a = g.nodes[n]
            col = cmap((a.get("region") or 0) % 20)
            if a["status"] == NodeStatus.VISITED:
                mk = "^" if n in d.scene.stairs else "o"
                ax.scatter(*a["pos"][:2], s=22, color=col, edgecolors="k", linewidths=0.4, marker=mk, zorder=3)
            elif a["status"] == NodeStatus.UNREACHABLE:
                ax.scatter(*a["pos"][:2], s=14, marker="x", color="red", zorder=3)
        for pt in d.tours:
            if d.scene.region_floor[pt.tour.region] != fl.index:
                continue
            col = cmap(pt.tour.region % 20)
            path = np.asarray(pt.tour.path_m)
            ax.plot(path[:, 0], path[:, 1], color=col, lw=2.0, zorder=4)
            hubs = np.asarray(pt.tour.hubs_m)
            ax.scatter(hubs[:, 0], hubs[:, 1], marker="*", s=160, color=col, edgecolors="k", zorder=5)
            ax.annotate(f"R{pt.tour.region} {pt.tour.coverage:.2f}", hubs[0, :2], fontsize=8, zorder=6)
        ax.set_title(f"floor {fl.index} (z={fl.z_m:.2f} m)")
        ax.set_aspect("equal")
        # Zoom on what was explored: the occupancy grid is padded by the sensor range.
        known = np.argwhere(occ.cells != 0)
        if len(known):
            lo = occ.origin_m + known.min(axis=0) * occ.cell_m - 0.5
            hi = occ.origin_m + (known.max(axis=0) + 1) * occ.cell_m + 0.5
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    handles = [
        Line2D([], [], marker="o", ls="", color="0.6", mec="k", label="visited node (colour = region)"),
        Line2D([], [], marker="^", ls="", color="0.6", mec="k", label="stair node"),
        Line2D([], [], marker="x", ls="", color="red", label="unreachable candidate"),
        Line2D([], [], color="0.45", lw=0.8, label="traversed edge"),
        Line2D([], [], marker="*", ls="-", ms=12, color="tab:blue", mec="k", label="hubs + tour (label: region, coverage)"),
        Patch(facecolor="white", edgecolor="0.5", label="free"),
        Patch(facecolor="0.1", label="occupied"),
        Patch(facecolor="0.75", label="unknown"),
    ]
    ncol = 4 if len(floors) > 1 else 2
    fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    fig.suptitle(f"{d.result.steps} steps, {len(d.scene.regions)} regions, {len(d.tours)} tours")
    fig.tight_layout(rect=(0, 0.07 if len(floors) > 1 else 0.13, 1, 1))
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png


def main() -> None:
    ap = argparse.ArgumentParser(description="mapper debug picture")
    ap.add_argument("--scene", default="generated:0", help="'boxworld' or a robot-io sim scene")
    ap.add_argument("--out", default="out/mapper")
    ap.add_argument("--size", type=int, default=64, help="panorama view size in pixels")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.scene == "boxworld":
        from services.mapper.tools.boxworld import BoxWorldRobot, rooms_world

        robot = BoxWorldRobot(rooms_world(), PinholeCamera(args.size, args.size, 90.0))
    else:
        from services.robot_io.core.robot import ROBOTS

        cam = CameraIntrinsics(width_px=args.size, height_px=args.size, hfov_deg=90.0)
        robot = ROBOTS.create("sim", {"scene": args.scene, "camera": cam})
    d = discover(robot)
    name = args.scene.replace(":", "_").replace("=", "-").replace("/", "_")
    print(render(d, Path(args.out) / f"mapper_{name}.png"))


if __name__ == "__main__":
    main()
