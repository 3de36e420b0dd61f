"""A flaky robot link (issue 34, item 5): the ROS 2 stand-in runs in its own network namespace, joined
to robot-io's backend by a veth pair. Then:

* netem 100 ms delay + 5 % loss on the link: commands still complete or end in a typed error;
* a 10 s partition (the veth taken down) in the middle of a turn: the turn ends in a typed error, the
  robot stops (the driver's watchdog: no Twist arrives), and once healed no command queued during the
  partition is applied late (the robot stays where it stopped until told to move);
* after healing, the next command succeeds. Nothing hangs: every wait is bounded.

Needs root, ``ip netns`` and (for the delay/loss phase) the kernel's netem qdisc; skipped with the reason
where a piece is missing.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time

import pytest

from deploy.launcher import STANDIN_PROFILE_OVERRIDES, free_port
import services.robot_io.ros2_zenoh  # noqa: F401  (registers the zenoh transport)
from services.robot_io.core.ros2.backend import Ros2Config, Ros2Error, Ros2Robot
from tests.waiting import wait_until

pytestmark = pytest.mark.system  # the stand-in as its own process, in a network namespace

# A small house: the link's faults do not depend on the scene, and the stand-in starts (builds its house,
# nav grid and kernels) for every test.
SCENE = "generated:3:area=50"
TAG = f"ant{os.getpid() % 100000}"
NS, VH, VR = f"{TAG}ns", f"{TAG}h", f"{TAG}r"
HOST_IP, ROBOT_IP = "10.213.7.1", "10.213.7.2"


def _sh(*argv: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=20, check=check)


def _why_not() -> str | None:
    if os.geteuid() != 0:
        return "needs root (network namespaces, veth)"
    if not shutil.which("ip") or not shutil.which("tc"):
        return "needs iproute2 (ip, tc)"
    probe = f"{TAG}p"
    r = _sh("ip", "netns", "add", probe, check=False)
    if r.returncode:
        return f"ip netns unavailable: {r.stderr.strip()}"
    _sh("ip", "netns", "del", probe, check=False)
    return None


def _netem_missing() -> str | None:
    a, b = f"{TAG}x0", f"{TAG}x1"
    r = _sh("ip", "link", "add", a, "type", "veth", "peer", "name", b, check=False)
    if r.returncode:
        return f"veth unavailable: {r.stderr.strip()}"
    try:
        q = _sh("tc", "qdisc", "add", "dev", a, "root", "netem", "delay", "100ms", check=False)
        return None if q.returncode == 0 else f"netem unavailable in this kernel: {q.stderr.strip()}"
    finally:
        _sh("ip", "link", "del", a, check=False)


@pytest.fixture
def link():
    why = _why_not()
    if why:
        pytest.skip(why)
    _sh("ip", "netns", "add", NS)
    try:
        _sh("ip", "link", "add", VH, "type", "veth", "peer", "name", VR)
        _sh("ip", "link", "set", VR, "netns", NS)
        _sh("ip", "addr", "add", f"{HOST_IP}/30", "dev", VH)
        _sh("ip", "link", "set", VH, "up")
        _sh("ip", "netns", "exec", NS, "ip", "addr", "add", f"{ROBOT_IP}/30", "dev", VR)
        _sh("ip", "netns", "exec", NS, "ip", "link", "set", VR, "up")
        _sh("ip", "netns", "exec", NS, "ip", "link", "set", "lo", "up")
        yield
    finally:
        _sh("ip", "link", "del", VH, check=False)
        _sh("ip", "netns", "del", NS, check=False)


@pytest.fixture
def standin(link):
    port = free_port()
    endpoint = f"tcp/{ROBOT_IP}:{port}"
    cfg = {"time_scale": 4.0, "camera": {"width_px": 32, "height_px": 32}}
    proc = subprocess.Popen(
        ["ip", "netns", "exec", NS, sys.executable, "-m", "services.robot_io.tools.ros2_robot", "--scene", SCENE,
         "--keys", "bridge", "--listen", endpoint, "--profile-overrides", json.dumps(STANDIN_PROFILE_OVERRIDES),
         "--config", json.dumps(cfg)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = wait_until(lambda: (lambda s: s if "ready" in s or proc.poll() is not None else None)(
            proc.stdout.readline()), 120, "the stand-in's ready line")
        assert "ready" in line, line
        yield endpoint
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _backend(endpoint: str) -> Ros2Robot:
    # Odometry may be 4 s of robot time old (1 s of wall time at the stand-in's scale of 4): at 2 s the
    # healthy link's first turn failed as stale (2.13 s) with the machine's two cores busy (the system tier
    # runs two tests at once). The partition does not depend on it: with the link down no /clock arrives,
    # robot time stands still, and the turn ends on the clock's silence (clock_timeout_s, wall time).
    return Ros2Robot(Ros2Config(profile="generic", profile_overrides=STANDIN_PROFILE_OVERRIDES, keys="bridge",
                                max_data_age_s=4.0, clock_timeout_s=5.0, connect_timeout_s=60,
                                transport_config={"zenoh": {"connect": [endpoint], "mode": "client"}}))


def _fresh(robot: Ros2Robot) -> bool:
    """Odometry newer than the allowed data age (the backend's own check raises when it is not)."""
    robot._fresh(robot._odom, robot.profile.odom)
    return True


def _heading(robot: Ros2Robot) -> float:
    return wait_until(lambda: robot.pose.heading_rad, 30, "a fresh pose", ignore=(Ros2Error,))


@pytest.fixture
def netem(link):
    """The kernel's netem qdisc, or a skip: asked before ``standin`` so that a kernel without it does not
    start a stand-in for nothing."""
    why = _netem_missing()
    if why:
        pytest.skip(why)


def test_delay_and_loss_leave_commands_complete_or_typed(netem, standin):
    _sh("tc", "qdisc", "add", "dev", VH, "root", "netem", "delay", "100ms", "loss", "5%")
    with _backend(standin) as robot:
        outcomes = []
        for k in range(4):  # bounded: four quarter turns
            try:
                robot.turn(math.pi / 2)
                outcomes.append("ok")
            except Ros2Error as exc:
                outcomes.append(type(exc).__name__)
        assert outcomes.count("ok") >= 2, outcomes  # a bad link slows commands; it does not break them all


def test_a_partition_mid_turn_is_a_typed_error_nothing_late_and_the_next_command_succeeds(standin):
    import threading

    with _backend(standin) as robot:
        robot.turn(0.3)  # the link works
        cut = threading.Timer(0.5, lambda: _sh("ip", "link", "set", VH, "down"))
        cut.start()
        t0 = time.monotonic()
        with pytest.raises(Ros2Error):
            robot.turn(4 * math.pi)  # ~seconds of turning; the partition comes half a second in
        ended_s = time.monotonic() - t0
        cut.join()
        time.sleep(max(0.0, 10.0 - ended_s))  # the partition lasts 10 s in all
        _sh("ip", "link", "set", VH, "up")
        # Healed: odometry flows again (the session reconnects), and the robot stands where the
        # watchdog stopped it: a Twist queued during the partition and applied now, or a command
        # still running, would turn it between two readings taken once the link is back.
        wait_until(lambda: _fresh(robot), 60,
                   "odometry after the partition", ignore=(Ros2Error,))
        time.sleep(2.0)
        h1 = _heading(robot)
        time.sleep(1.0)
        h2 = _heading(robot)
        assert abs(math.remainder(h2 - h1, 2 * math.pi)) < math.radians(3)
        # The next command succeeds.
        pose = robot.turn(0.5)
        assert abs(math.remainder(pose.heading_rad - h2 - 0.5, 2 * math.pi)) < math.radians(10)
