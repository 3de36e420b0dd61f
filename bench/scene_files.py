"""Benchmark of scene-file loading: Habitat's test assets and a large textured glTF.

    python -m bench.scene_files [--repeats 5] [--grid 350]

Per file: median wall time of ``load_scene`` (frame resolution, geometry, materials and textures,
semantics lookup) and, for glTF files, of open3d's ``read_triangle_model`` (assimp) on the same
file for comparison. The large file is generated: a (grid x grid x 2)-triangle terrain with one
2048 x 2048 texture, the size class of a Matterport region.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import table
from libs.world.scene import load_scene
from shared.o3d import o3d

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ASSETS = ["habitat_test_assets/simple_room.glb", "habitat_test_assets/stage_floor1.glb", "habitat_test_assets/chair.glb",
          "habitat_test_assets/fridge_body.glb", "replica_office0/office0_mesh.ply"]


def _median_ms(fn, repeats: int) -> float:
    walls = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        walls.append((time.perf_counter() - t) * 1e3)
    return statistics.median(walls)


def _terrain(path: Path, grid: int) -> Path:
    from tests.unit.robot_io.gltf_files import Primitive, write_glb

    x, y = np.meshgrid(np.linspace(0, 20, grid + 1), np.linspace(0, 20, grid + 1))
    v = np.stack([x.ravel(), (0.2 * np.sin(x) * np.cos(y)).ravel(), y.ravel()], 1)
    r = (np.arange(grid * grid) // grid) * (grid + 1) + np.arange(grid * grid) % grid
    t = np.concatenate([np.stack([r, r + grid + 1, r + 1], -1), np.stack([r + 1, r + grid + 1, r + grid + 2], -1)])
    tex = (np.random.default_rng(0).random((2048, 2048, 3)) * 255).astype(np.uint8)
    return write_glb(path, [Primitive(v, t, uvs=np.stack([x.ravel(), y.ravel()], 1) / 20, texture=tex)])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--grid", type=int, default=350)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        files = [DATA / a for a in ASSETS if (DATA / a).is_file()] + [_terrain(Path(tmp) / "terrain.glb", args.grid)]
        rows = []
        for f in files:
            scene = load_scene(str(f))
            ours = _median_ms(lambda: load_scene(str(f)), args.repeats)
            assimp = _median_ms(lambda: o3d.io.read_triangle_model(str(f)), args.repeats) if f.suffix == ".glb" else float("nan")
            rows.append((f.name, len(scene.triangles), "yes" if scene.texture is not None else "no", ours, assimp))
    table("scene files: load_scene vs open3d read_triangle_model (median ms)", rows,
          ("file", "triangles", "textured", "load_scene ms", "open3d model ms"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
