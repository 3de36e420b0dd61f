"""A scene's layout: its labelled rooms and objects (what instructions name). Apart from scene.py so that
the scene's builders and readers (the house generator, the semantics readers) can make rooms and
objects without importing the scene module that imports them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Room:
    """A room of a floor plan: an axis-aligned box on the floor of storey ``floor``."""

    name: str  # unique, e.g. "bedroom 2"
    room_type: str  # bedroom, kitchen, bathroom, living room, hallway, office, dining room, staircase
    floor: int
    min_xy_m: tuple[float, float]
    max_xy_m: tuple[float, float]
    floor_z_m: float = 0.0

    @property
    def area_m2(self) -> float:
        return (self.max_xy_m[0] - self.min_xy_m[0]) * (self.max_xy_m[1] - self.min_xy_m[1])

    @property
    def centre_m(self) -> np.ndarray:
        return np.array(
            [
                (self.min_xy_m[0] + self.max_xy_m[0]) / 2.0,
                (self.min_xy_m[1] + self.max_xy_m[1]) / 2.0,
                self.floor_z_m,
            ]
        )

    def contains(self, p: np.ndarray, z_tol_m: float = 1.0) -> bool:
        p = np.asarray(p, dtype=np.float64)
        return bool(
            self.min_xy_m[0] <= p[0] <= self.max_xy_m[0]
            and self.min_xy_m[1] <= p[1] <= self.max_xy_m[1]
            and abs(p[2] - self.floor_z_m) <= z_tol_m
        )


@dataclass(frozen=True)
class SceneObject:
    """A piece of furniture: class label, colour name (for instructions), room and box."""

    object_id: int
    label: str
    colour: str
    room: str
    position_m: tuple[float, float, float]  # centre of the footprint, on the floor
    size_m: tuple[float, float, float]  # extent along world x, y, z
    yaw_rad: float = 0.0

    @property
    def description(self) -> str:
        return f"{self.colour} {self.label}" if self.colour else self.label
