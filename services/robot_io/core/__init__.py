"""robot-io core: the robot port, the embedded simulator, scenes, navigation grid and episodes.

Pure Python (numpy / open3d / scipy / networkx); never imports zenoh. The bus adapter
(``services/robot_io/service.py``) decodes requests, calls these objects and encodes replies.
"""

from .episodes import Episode, EpisodeDataset, generate_episodes, read_episodes, write_episodes
from .errors import (
    EpisodeFormatError,
    EpisodeGenerationError,
    NavigationError,
    RobotIOError,
    SceneError,
    SceneFormatError,
    SceneNotFoundError,
)
from .house import HouseSpec, generate_house
from .navgrid import AgentShape, NavGrid
from .render import Intrinsics, RenderOutput, SceneRenderer
from .robot import ROBOTS, Robot, SimConfig, SimRobot
from .scene import Room, Scene, SceneObject, load_scene
from .sensors import SensorNoiseConfig

__all__ = [
    "ROBOTS", "AgentShape", "Episode", "EpisodeDataset", "EpisodeFormatError", "EpisodeGenerationError",
    "HouseSpec", "Intrinsics", "NavGrid", "NavigationError", "RenderOutput", "Robot", "RobotIOError", "Room",
    "Scene", "SceneError", "SceneFormatError", "SceneNotFoundError", "SceneObject", "SceneRenderer",
    "SensorNoiseConfig", "SimConfig", "SimRobot", "generate_episodes", "generate_house", "load_scene",
    "read_episodes", "write_episodes",
]
