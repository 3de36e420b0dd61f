"""Typed errors of the robot-io core; the bus adapter maps them to ``ErrorReply`` codes.

The world's errors (scenes, navigation, episodes) live with the world library (``libs.world.errors``)
and the ROS 2 protocol's with it (``libs.ros2.errors``); ``REFUSALS`` is every base the service answers
as a refused request rather than an internal fault.
"""

from __future__ import annotations

from libs.ros2.errors import Ros2ProtocolError
from libs.world.errors import WorldError


class RobotIOError(Exception):
    """Base of every error raised by the robot-io core itself (the robot port and its backends)."""


REFUSALS: tuple[type[Exception], ...] = (RobotIOError, WorldError, Ros2ProtocolError)
