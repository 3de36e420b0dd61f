"""The ROS 2 protocol library's typed errors: one base, so a caller catches the library's refusals in
one clause and maps them to its own codes (robot-io answers them as a refused request)."""

from __future__ import annotations


class Ros2ProtocolError(Exception):
    """Base of every error raised by ``libs.ros2``: a malformed message, name or profile."""
