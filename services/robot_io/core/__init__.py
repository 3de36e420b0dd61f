"""robot-io core: the robot port, the embedded simulator, scenes, navigation grid and episodes.

Pure Python (numpy / open3d / scipy / networkx); never imports zenoh. The bus adapter
(``services/robot_io/service.py``) decodes requests, calls these objects and encodes replies.
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
    RobotIOError,
    SceneError,
    SceneFormatError,
    SceneNotFoundError,
)
from .house import HouseSpec, generate_house
from .info import describe_scene
from .navgrid import AgentShape, NavGrid
from .render import Intrinsics, RenderOutput, SceneRenderer
from .robot import ROBOTS, Robot, SimConfig, SimRobot
# The ROS 2 backend registers itself as "ros2" in ROBOTS (its zenoh transport: services/robot_io/ros2_zenoh.py).
from .ros2 import backend as _ros2_backend  # noqa: E402,F401
from .scene import Room, Scene, SceneObject, load_scene
from .sensors import SensorNoiseConfig

__all__ = [
    "ROBOTS", "AgentShape", "Episode", "EpisodeDataset", "EpisodeFormatError", "EpisodeGenerationError",
    "GroundTruth", "HouseSpec", "Intrinsics", "NavGrid", "NavigationError", "NoWalkableAreaError", "PoseOffGroundError", "RenderOutput", "Robot",
    "RobotIOError", "Room", "Scene", "SceneError", "SceneFormatError", "describe_scene", "SceneNotFoundError",
    "SceneObject", "SceneRenderer", "SensorNoiseConfig", "SimConfig", "SimRobot", "follow_path", "generate_episodes",
    "generate_house", "ground_truth_for", "load_scene", "read_episodes", "read_ground_truth", "write_episodes",
    "write_ground_truth",
]
