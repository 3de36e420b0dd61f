"""A simulated-world library: scenes (generated houses, glTF/GLB, PLY scans, Habitat configs), their
rooms and objects, the navigation grid and R2R-CE style episodes.

Pure Python (numpy / open3d / scipy); imports only ``shared/``. Robot-io's simulator stands on it, and
so do evaluation, bench and deploy, which build scenes and episodes without a robot.
"""

from .episodes import (
    Episode,
    EpisodeDataset,
    GroundTruth,
    follow_path,
    generate_episodes,
    ground_truth_for,
    read_episodes,
    read_ground_truth,
    write_episodes,
    write_ground_truth,
)
from .errors import (
    EpisodeFormatError,
    EpisodeGenerationError,
    NavigationError,
    NoWalkableAreaError,
    PoseOffGroundError,
    SceneError,
    SceneFormatError,
    SceneNotFoundError,
    WorldError,
)
from .house import HouseSpec, generate_house
from .info import describe_scene
from .navgrid import AgentShape, NavGrid
from .scene import Room, Scene, SceneObject, load_scene

__all__ = [
    "AgentShape", "Episode", "EpisodeDataset", "EpisodeFormatError", "EpisodeGenerationError", "GroundTruth",
    "HouseSpec", "NavGrid", "NavigationError", "NoWalkableAreaError", "PoseOffGroundError", "Room", "Scene",
    "SceneError", "SceneFormatError", "SceneNotFoundError", "SceneObject", "WorldError", "describe_scene",
    "follow_path", "generate_episodes", "generate_house", "ground_truth_for", "load_scene", "read_episodes",
    "read_ground_truth", "write_episodes", "write_ground_truth",
]
