"""An rmw_zenoh client nobody here wrote checks our stand-in (issue 34, item 7): ``zenoh-ros2-sdk``
(PyPI, Apache-2.0) lists our topics with their types from the liveliness tokens, computes its own
RIHS01 type hashes to build the keys, decodes our odometry, and drives the stand-in over cmd_vel.

It is given the .msg files (written from rosbags' Jazzy type store) so that it fetches nothing."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import pytest

sdk = pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk (test dependency, requirements.lock) not installed")

from rosbags.typesys import Stores, get_typestore  # noqa: E402
from rosbags.typesys.store import Nodetype  # noqa: E402

from deploy.launcher import free_port  # noqa: E402
from libs.ros2.keys import key_style  # noqa: E402
from libs.ros2.profiles import profile  # noqa: E402
from services.robot_io.core.ros2.standin import StandInConfig, StandInRobot  # noqa: E402
from services.robot_io.ros2_zenoh import ZenohRos2Transport, ZenohTransportConfig  # noqa: E402
from shared.bus.config import ZenohSettings  # noqa: E402
from tests.waiting import wait_until  # noqa: E402

pytestmark = pytest.mark.contract


def _field_type(node) -> str:
    kind, arg = node
    if kind == Nodetype.BASE:
        return arg[0] if not arg[1] else f"{arg[0]}<={arg[1]}"
    if kind == Nodetype.NAME:
        pkg, _msg, name = arg.split("/")
        return f"{pkg}/{name}"
    sub, n = arg
    if kind == Nodetype.ARRAY:
        return f"{_field_type(sub)}[{n}]"
    return f"{_field_type(sub)}[]" if not n else f"{_field_type(sub)}[<={n}]"


def write_msg_files(root: Path, types: list[str]) -> None:
    """The .msg files of ``types`` and everything they contain, from rosbags' Jazzy store."""
    store = get_typestore(Stores.ROS2_JAZZY)
    todo, done = list(types), set()
    while todo:
        name = todo.pop()
        if name in done:
            continue
        done.add(name)
        consts, fields = store.fielddefs[name]
        lines = [f"{t} {n}={v}" for n, t, v in consts]
        for fname, node in fields:
            lines.append(f"{_field_type(node)} {fname}")
            inner = node
            while inner[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
                inner = inner[1][0]
            if inner[0] == Nodetype.NAME:
                todo.append(inner[1])
        pkg, msg, short = name.split("/")
        path = root / pkg / msg / f"{short}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n")


@pytest.fixture
def standin():
    port = free_port()
    t = ZenohRos2Transport(ZenohTransportConfig(zenoh=ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"])))
    cfg = StandInConfig(scene="generated:0", time_scale=4.0, camera={"width_px": 32, "height_px": 32})
    robot = StandInRobot(cfg, profile("generic", {"clock": "/clock"}), t, key_style("rmw_zenoh"))
    th = threading.Thread(target=robot.run, daemon=True)
    th.start()
    yield robot, port
    robot.stop()
    th.join(5)
    robot.close()
    t.close()


def test_an_independent_rmw_zenoh_client_lists_decodes_and_drives_the_stand_in(standin, tmp_path):
    robot, port = standin
    from zenoh_ros2_sdk import message_registry, session

    write_msg_files(tmp_path, ["nav_msgs/msg/Odometry", "geometry_msgs/msg/Twist"])
    message_registry._registry = None  # the SDK's process-wide registry: ours, with our files
    message_registry.get_registry(str(tmp_path))
    session.ZenohSession._instance = None
    subs, pubs = [], []
    try:
        topics = dict(wait_until(lambda: (lambda t: t if "/odom" in dict(t) else None)(
            sdk.get_topic_names_and_types(router_port=port, timeout=1.0)), 30, "our topics in the SDK's graph"))
        assert "nav_msgs/msg/Odometry" in topics["/odom"]
        assert "geometry_msgs/msg/Twist" in topics["/cmd_vel"]

        odoms = []
        subs.append(sdk.ROS2Subscriber("/odom", "nav_msgs/msg/Odometry", odoms.append, router_port=port))
        wait_until(lambda: len(odoms) >= 5, 30, "odometry decoded by the SDK")
        o = odoms[-1]
        p = robot.true_pose.position_m
        assert abs(o.pose.pose.position.x - p[0]) < 0.5 and abs(o.pose.pose.position.y - p[1]) < 0.5
        assert o.header.frame_id and o.child_frame_id

        pub = sdk.ROS2Publisher("/cmd_vel", "geometry_msgs/msg/Twist", router_port=port)
        pubs.append(pub)
        vec = message_registry.get_registry().get_message_class("geometry_msgs/msg/Vector3")
        before, yaw0 = robot.stats.nonzero_cmd, robot.true_pose.heading_rad

        def drive():
            pub.publish(linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.4))
            return robot.stats.nonzero_cmd >= before + 20

        wait_until(drive, 30, "the stand-in to take the SDK's Twists", interval_s=0.05)
        pub.publish(linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
        # The SDK's Twists turned the robot (the stand-in integrated them), anticlockwise.
        turned = math.remainder(robot.true_pose.heading_rad - yaw0, 2 * math.pi)
        assert turned > math.radians(5)
    finally:
        for x in subs + pubs:
            x.close()
        if session.ZenohSession._instance is not None:
            session.ZenohSession._instance.close()
        message_registry._registry = None
