"""Nav2 map round trip: write PGM + YAML, read them back with a plain reader (not the writer's code),
apply map_server's trinary rule and compare the occupancy with the cloud it came from."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from shared.export import FREE, OCCUPIED, UNKNOWN, OccupancyConfig, floor_z_of, nav2_files, occupancy_from_cloud


def read_pgm(data: bytes) -> np.ndarray:
    """A minimal binary PGM (P5) reader: magic, width, height, maxval with '#' comments, then bytes."""
    tokens: list[bytes] = []
    i = 0
    while len(tokens) < 4:
        while data[i:i + 1].isspace():
            i += 1
        if data[i:i + 1] == b"#":
            i = data.index(b"\n", i) + 1
            continue
        j = i
        while not data[j:j + 1].isspace():
            j += 1
        tokens.append(data[i:j])
        i = j
    i += 1  # exactly one whitespace byte after maxval
    assert tokens[0] == b"P5" and int(tokens[3]) == 255
    w, h = int(tokens[1]), int(tokens[2])
    return np.frombuffer(data, np.uint8, w * h, i).reshape(h, w)


def load_map_server(yaml_path: Path) -> tuple[np.ndarray, dict]:
    """map_server's reading of a trinary map: 100 occupied, 0 free, -1 unknown, row 0 = top."""
    meta = yaml.safe_load(yaml_path.read_text())
    img = read_pgm((yaml_path.parent / meta["image"]).read_bytes()).astype(np.float64)
    p = img / 255.0 if meta["negate"] else (255.0 - img) / 255.0
    out = np.full(img.shape, -1, np.int8)
    out[p > meta["occupied_thresh"]] = 100
    out[p < meta["free_thresh"]] = 0
    return out, meta


def world_to_cell(meta: dict, shape: tuple[int, int], x: float, y: float) -> tuple[int, int]:
    x0, y0, yaw = meta["origin"]
    assert yaw == 0.0
    res = meta["resolution"]
    col = int(math.floor((x - x0) / res))
    row = shape[0] - 1 - int(math.floor((y - y0) / res))
    return row, col


def room_cloud(seed: int = 0) -> np.ndarray:
    """A 4 m x 3 m room (floor at z = 0.3 m, walls to 2.4 m) with a 0.6 m box at (1, 1), and a few strays."""
    rng = np.random.default_rng(seed)
    fx, fy = rng.uniform(0, 4, 40_000), rng.uniform(0, 3, 40_000)
    floor = np.column_stack([fx, fy, np.full_like(fx, 0.3)])
    walls = []
    for _ in range(4):
        t, z = rng.uniform(0, 1, 8000), rng.uniform(0.3, 2.4, 8000)
        walls += [np.column_stack([4 * t, np.zeros_like(t), z]), np.column_stack([4 * t, np.full_like(t, 3.0), z]),
                  np.column_stack([np.zeros_like(t), 3 * t, z]), np.column_stack([np.full_like(t, 4.0), 3 * t, z])]
    bx, by, bz = rng.uniform(0.7, 1.3, 3000), rng.uniform(0.7, 1.3, 3000), rng.uniform(0.3, 1.2, 3000)
    box = np.column_stack([bx, by, bz])
    stray = np.array([[2.0, 1.5, -3.0]])  # one point far below the floor must not move the floor estimate
    return np.concatenate([floor, *walls, box, stray])


def test_nav2_round_trip_matches_the_cloud(tmp_path):
    xyz = room_cloud()
    assert floor_z_of(xyz) == pytest.approx(0.3, abs=0.05)
    grid = occupancy_from_cloud(xyz, config=OccupancyConfig(cell_m=0.05, margin_m=0.5))
    for name, data in nav2_files(grid, "room").items():
        (tmp_path / name).write_bytes(data)
    cells, meta = load_map_server(tmp_path / "room.yaml")

    assert meta["mode"] == "trinary" and meta["resolution"] == pytest.approx(0.05)
    assert set(meta) >= {"image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"}
    # What map_server reads is exactly the grid that was written, cell for cell ...
    np.testing.assert_array_equal(cells, grid.cells)
    assert {int(v) for v in np.unique(cells)} == {UNKNOWN, FREE, OCCUPIED}
    # ... and it is the room: placed in the world by the YAML's origin and resolution alone.
    def at(x, y):
        return int(cells[world_to_cell(meta, cells.shape, x, y)])

    for x, y in [(2.0, 0.0), (2.0, 3.0), (0.0, 1.5), (4.0, 1.5), (1.0, 1.0), (0.8, 1.2)]:
        assert at(x, y) == OCCUPIED, (x, y)
    for x, y in [(2.5, 1.5), (3.0, 2.5), (2.0, 0.5), (0.4, 2.6)]:
        assert at(x, y) == FREE, (x, y)
    for x, y in [(-0.4, -0.4), (4.4, 3.4), (-0.3, 1.5)]:
        assert at(x, y) == UNKNOWN, (x, y)
    # The interior free area is the room minus the box, within a cell's margin along every edge.
    free_area = float((cells == FREE).sum()) * 0.05**2
    assert 12.0 - 0.36 - 1.0 < free_area < 12.0


def test_unknown_stays_unknown_with_map_server_thresholds(tmp_path):
    """205 (unknown) lies between the thresholds: a reader must not take it for free."""
    grid = occupancy_from_cloud(room_cloud(), config=OccupancyConfig(cell_m=0.1))
    files = nav2_files(grid, "m")
    img = read_pgm(files["m.pgm"])
    meta = yaml.safe_load(files["m.yaml"])
    p = (255.0 - img[grid.cells == UNKNOWN]) / 255.0
    assert np.all((p >= meta["free_thresh"]) & (p <= meta["occupied_thresh"]))


def test_a_floor_above_gives_another_grid():
    xyz = room_cloud()
    upper = xyz + np.array([0.0, 0.0, 3.0])
    both = np.concatenate([xyz, upper[upper[:, 0] < 2.0]])  # the upper storey covers only x < 2
    low = occupancy_from_cloud(both)
    high = occupancy_from_cloud(both, floor_z_m=3.3)
    assert low.floor_z_m == pytest.approx(0.3, abs=0.05)
    assert (high.cells == FREE).sum() < 0.7 * (low.cells == FREE).sum()


def test_bad_input_is_refused():
    with pytest.raises(ValueError):
        occupancy_from_cloud(np.zeros((0, 3)))
    with pytest.raises(ValueError):
        occupancy_from_cloud(room_cloud(), floor_z_m=float("nan"))
    with pytest.raises(ValueError):
        OccupancyConfig(floor_band_m=(0.2, 0.1))
    with pytest.raises(ValueError, match="max_cells"):
        occupancy_from_cloud(np.array([[0, 0, 0], [1000, 1000, 0.0]]), config=OccupancyConfig(cell_m=0.01))
