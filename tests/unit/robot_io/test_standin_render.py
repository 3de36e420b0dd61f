"""The ROS 2 stand-in renders its camera and casts its scan again only when the robot has moved.

A base that stands still (the system reconstructing or planning) published the same images at the camera
rate and rendered every one of them: about a third of the stand-in's CPU while it stood. Every message is
still published at its rate, with its own stamp, and holds what a fresh render from that pose gives.
"""

from __future__ import annotations

import numpy as np
import pytest

from libs.ros2 import messages as m
from libs.ros2.keys import key_style
from libs.ros2.profiles import STANDIN_OVERRIDES, profile
from libs.ros2.transport import Ros2Transport
from services.robot_io.core.ros2.standin import StandInConfig, StandInRobot


class _Recorder:
    def __init__(self, key: str, sink: dict[str, list[bytes]]):
        self.key, self.sink = key, sink

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self.sink.setdefault(self.key, []).append(payload)

    def close(self) -> None:
        pass


class _RecordingTransport(Ros2Transport):
    """Keeps every published payload by key; nothing is delivered anywhere (the stand-in only publishes here)."""

    def __init__(self):
        self.sent: dict[str, list[bytes]] = {}

    @property
    def session_id(self) -> str:
        return "0123456789abcdef"

    def publisher(self, key, *, reliable=True, keep_last=0):
        return _Recorder(key, self.sent)

    def subscribe(self, key, handler, *, max_queue=8, transient_local=False):
        return _Recorder(key, {})

    def query(self, key, payload, attachment, timeout_s):
        raise AssertionError("the stand-in asks nothing")

    def serve(self, key, handler):
        return _Recorder(key, {})

    def token(self, key):
        return _Recorder(key, {})

    def close(self) -> None:
        pass


CAMERA_RATE_HZ, CONTROL_RATE_HZ = 5.0, 20.0


@pytest.fixture(scope="module")
def standin():
    t = _RecordingTransport()
    cfg = StandInConfig.model_validate({"scene": "generated:3:area=50", "camera": {"width_px": 32, "height_px": 24},
                                        "camera_rate_hz": CAMERA_RATE_HZ, "control_rate_hz": CONTROL_RATE_HZ,
                                        "scan_beams": 64})
    robot = StandInRobot(cfg, profile("generic", STANDIN_OVERRIDES), t, key_style("rmw_zenoh"))
    renders, casts = [], []
    render_views, first_hit = robot.sim.renderer.render_views, robot.sim.renderer.first_hit_distance
    robot.sim.renderer.render_views = lambda *a, **k: renders.append(1) or render_views(*a, **k)
    robot.sim.renderer.first_hit_distance = lambda *a, **k: casts.append(1) or first_hit(*a, **k)
    yield robot, t, renders, casts, render_views
    robot.close()


def _key(robot, topic: str, type_key: str) -> str:
    return robot.node.keys.topic_key(topic, m.RosType(m.MESSAGES[type_key]))


def _images(robot, t, topic: str) -> list:
    return [m.decode(m.MESSAGES["image"], b) for b in t.sent.get(_key(robot, topic, "image"), [])]


def _fresh_view(robot, render_views):
    """What the camera sees from the stand-in's pose now, rendered afresh."""
    p, cam = robot.profile, robot.config.camera
    return render_views(robot._pos, np.array([robot._heading]), cam.pinhole(), 0.0, p.camera_height_m,
                        with_semantic=True)


def test_a_still_robot_publishes_every_frame_at_its_rate_but_renders_once(standin):
    robot, t, renders, casts, render_views = standin
    t.sent.clear()
    n0, r0, c0 = robot.stats.images, len(renders), len(casts)
    ticks = int(4 * CONTROL_RATE_HZ)  # 4 s of simulated time
    for _ in range(ticks):
        robot.step()
    frames = robot.stats.images - n0
    assert frames >= 4 * CAMERA_RATE_HZ - 1  # the camera's rate, as before
    colour, depth = _images(robot, t, robot.profile.color), _images(robot, t, robot.profile.depth)
    assert len(colour) == len(depth) == frames
    assert len({(c.header.stamp.sec, c.header.stamp.nanosec) for c in colour}) == frames  # each its own instant
    assert len(renders) - r0 <= 1 and len(casts) - c0 <= 1  # standing still: at most the first one renders
    view = _fresh_view(robot, render_views)
    for c, d in zip(colour, depth):
        assert np.array_equal(m.image_array(c), view.rgb[0])
        assert np.array_equal(m.image_array(d), np.where(np.isfinite(view.depth_m[0]), view.depth_m[0], 0.0))


def test_after_a_move_the_images_are_rendered_from_the_new_pose(standin):
    robot, t, renders, casts, render_views = standin
    for _ in range(3):
        robot.step()
    before = _fresh_view(robot, render_views).rgb[0]
    nav = robot.sim.nav
    rng = np.random.default_rng(3)
    far = next(p for p in nav.sample_navigable(rng, 50) if np.linalg.norm(p[:2] - robot._pos[:2]) > 1.5)
    robot._on_teleport(m.new("turtlesim/srv/TeleportAbsolute_Request", x=float(far[0]), y=float(far[1]),
                             theta=float(robot._heading) + 1.0))
    t.sent.clear()
    r0, c0 = len(renders), len(casts)
    for _ in range(int(CONTROL_RATE_HZ)):
        robot.step()
    colour = _images(robot, t, robot.profile.color)
    assert colour and len(renders) - r0 == 1 and len(casts) - c0 == 1
    after = _fresh_view(robot, render_views).rgb[0]
    assert not np.array_equal(after, before)  # the place really looks different
    assert all(np.array_equal(m.image_array(c), after) for c in colour)
    # Driving: a new pose every tick, so every frame is rendered again.
    r0 = len(renders)
    n0 = robot.stats.images
    for _ in range(int(CONTROL_RATE_HZ)):
        with robot._lock:
            robot._cmd = (0.0, 0.5, robot.t_s)  # turning in place never collides
        robot.step()
    assert robot.stats.images - n0 >= 4 and len(renders) - r0 == robot.stats.images - n0
