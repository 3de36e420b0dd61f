"""robot-io core: the robot port, its backends (the embedded simulator, ROS 2) and the simulator camera.

Pure Python (numpy / open3d / scipy); never imports zenoh. The bus adapter
(``services/robot_io/service.py``) decodes requests, calls these objects and encodes replies. Scenes,
the navigation grid and episodes are the world library's (``libs.world``); the ROS 2 protocol is
``libs.ros2``.
"""

from .errors import REFUSALS, RobotIOError
from .render import Intrinsics, RenderOutput, SceneRenderer
from .robot import ROBOTS, Robot, SimConfig, SimRobot

# The ROS 2 backend registers itself as "ros2" in ROBOTS (its zenoh transport: services/robot_io/ros2_zenoh.py).
from .ros2 import backend as _ros2_backend  # noqa: E402,F401
from .sensors import SensorNoiseConfig

__all__ = [
    "REFUSALS", "ROBOTS", "Intrinsics", "RenderOutput", "Robot", "RobotIOError", "SceneRenderer",
    "SensorNoiseConfig", "SimConfig", "SimRobot",
]
