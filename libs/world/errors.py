"""The simulated world's typed errors: scenes, navigation and episodes. One base (``WorldError``),
so a user of the library (robot-io, evaluation, bench) maps every refusal in one clause."""

from __future__ import annotations

from pathlib import Path


class WorldError(Exception):
    """Base of every error raised by ``libs.world``."""


class SceneError(WorldError):
    """A scene could not be built or loaded."""


class SceneNotFoundError(SceneError, FileNotFoundError):
    """A scene file does not exist; names the file and the configured scenes directory."""

    def __init__(self, path: Path | str, scenes_dir: Path | str | None):
        self.path = Path(path)
        self.scenes_dir = Path(scenes_dir) if scenes_dir is not None else None
        where = f"configured scenes directory: {self.scenes_dir}" if self.scenes_dir else "no scenes directory configured"
        super().__init__(f"scene file not found: {self.path} ({where})")

    def __str__(self) -> str:
        return self.args[0]


class SceneFormatError(SceneError):
    """A scene file exists but holds no usable triangle mesh, or a scene spec is malformed."""


class NavigationError(WorldError):
    """A navigation query cannot be answered (e.g. a point far from any walkable surface)."""


class PoseOffGroundError(NavigationError, ValueError):
    """A pose asked for lies farther from walkable ground than the tolerance (a ``ValueError``: the
    caller's input is wrong, answered ``bad_request``)."""

    def __init__(self, distance_m: float, tolerance_m: float):
        super().__init__(f"the pose is {distance_m:.2f} m from walkable ground (tolerance {tolerance_m:.2f} m)")
        self.distance_m, self.tolerance_m = distance_m, tolerance_m


class NoWalkableAreaError(SceneError, NavigationError, ValueError):
    """A scene has nowhere this agent can stand (only a ceiling or walls, a floor smaller than the
    agent, no headroom). Also a ``ValueError``: the caller named an unusable scene, so the bus
    answers ``bad_request`` rather than ``internal``."""


class EpisodeFormatError(WorldError):
    """An episode file does not follow the R2R-CE / RxR-CE format."""


class EpisodeGenerationError(WorldError):
    """No episode satisfying the requested constraints could be generated."""
