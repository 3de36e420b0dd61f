"""Robot profiles: the localisation frame's rules (the backend and the stand-in read the same profile)."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from libs.ros2.profiles import PROFILES, profile


def test_a_localisation_frame_needs_the_tf_topic_and_a_frame_of_its_own():
    assert profile("generic", {"map_frame": "map"}).map_frame == "map"
    with pytest.raises(ValidationError, match="needs the tf topic"):
        profile("generic", {"map_frame": "map", "tf": None})
    for same in ("odom", "/odom", "", "/"):
        with pytest.raises(ValidationError, match="other than odom_frame"):
            profile("generic", {"map_frame": same})


def test_stretch_reads_its_pose_from_localisation_and_generic_from_odometry():
    # Stretch's profile consumes /map, which only a localiser (AMCL, slam_toolbox) makes sense of.
    assert PROFILES["stretch"].map and PROFILES["stretch"].map_frame == "map"
    assert PROFILES["generic"].map_frame is None
