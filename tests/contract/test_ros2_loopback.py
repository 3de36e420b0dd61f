"""The ROS 2 stand-in and every ROS 2 helper listen on loopback unless told otherwise (issue 34,
item 4): zenoh's own default for a peer is ``tcp/[::]:0``, every interface, which would put a
robot's cmd_vel on the building's network. Checked on the process's real listening sockets."""

from __future__ import annotations

import psutil
import pytest

from services.robot_io.ros2_zenoh import ZenohRos2Transport, ZenohTransportConfig, loopback_unless_told
from services.robot_io.tools.ros2_robot import bus_settings
from shared.bus.config import ZenohSettings


def _listening() -> set[tuple[str, int]]:
    return {(c.laddr.ip, c.laddr.port) for c in psutil.Process().net_connections(kind="tcp")
            if c.status == psutil.CONN_LISTEN}


def _opened_by(settings: ZenohSettings) -> set[tuple[str, int]]:
    before = _listening()
    t = ZenohRos2Transport(ZenohTransportConfig(zenoh=settings))
    try:
        return _listening() - before
    finally:
        t.close()


def test_a_peer_told_nothing_listens_on_loopback_only():
    opened = _opened_by(ZenohSettings(mode="peer"))
    assert opened, "the peer listens somewhere (else the check below proves nothing)"
    assert {ip for ip, _ in opened} == {"127.0.0.1"}


def test_a_peer_told_to_listen_everywhere_does():
    opened = _opened_by(ZenohSettings(mode="peer", listen=["tcp/0.0.0.0:0"]))
    assert {ip for ip, _ in opened} == {"0.0.0.0"}


@pytest.mark.parametrize("argv,expected", [
    ([], ["tcp/127.0.0.1:0"]),  # the stand-in's command line with no --listen
    (["--listen", "tcp/0.0.0.0:7448"], ["tcp/0.0.0.0:7448"]),
])
def test_the_standin_command_line_defaults_to_loopback(argv, expected):
    import argparse

    ap = argparse.ArgumentParser()
    for flag in ("--connect", "--listen"):
        ap.add_argument(flag, action="append", default=[])
    for flag in ("--username", "--password-file", "--mode"):
        ap.add_argument(flag, default=None)
    assert loopback_unless_told(bus_settings(ap.parse_args(argv))).listen == expected


def test_a_client_listens_on_nothing():
    assert loopback_unless_told(ZenohSettings(mode="client", connect=["tcp/127.0.0.1:7447"])).listen == []
