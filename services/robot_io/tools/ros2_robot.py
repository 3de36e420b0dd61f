"""The ROS 2 stand-in robot: the embedded simulator behind ROS 2 messages over zenoh.

    python -m services.robot_io.tools.ros2_robot --scene generated:0 --keys bridge \
        --connect tcp/127.0.0.1:7447 [--profile generic|stretch] [--time-scale 5]

It speaks only ROS 2 (CDR over zenoh, in the zenoh-bridge-ros2dds or rmw_zenoh key style), so the
``ros2`` robot backend runs against it exactly as against a robot. Stops cleanly on SIGTERM/Ctrl-C.

On an authenticated bus it joins as the ROS 2 side's user (``ros2_robot``, see deploy/zenoh/acl.py), as a
real robot's bridge would: ``--username ros2_robot --password-file creds/ros2_robot.password``, or the
``ANT_ZENOH__*`` environment the services read (``ANT_ZENOH__MODE=client``, ``ANT_ZENOH__USERNAME``,
``ANT_ZENOH__PASSWORD_FILE``); the flags override the environment.
"""

from __future__ import annotations

import argparse
import json
import math
import logging
import signal
import sys
import threading

from libs.ros2.keys import key_style
from libs.ros2.profiles import PROFILES, profile
from services.robot_io.core.ros2.standin import StandInConfig, StandInRobot
from services.robot_io.ros2_zenoh import ZenohRos2Transport, ZenohTransportConfig, env_zenoh_settings
from shared.bus.config import ZenohSettings
from shared.logs import configure_logging
from shared.runner import freeze_started_heap

log = logging.getLogger("ros2_robot")


def bus_settings(args: argparse.Namespace) -> ZenohSettings:
    """The environment's zenoh settings with the command line's on top."""
    flags = {"connect": args.connect, "listen": args.listen, "username": args.username,
             "password_file": args.password_file, "mode": args.mode or ("client" if args.username else None)}
    return env_zenoh_settings().model_copy(update={k: v for k, v in flags.items() if v})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="generated:0")
    ap.add_argument("--scenes-dir", default=None)
    ap.add_argument("--keys", choices=["bridge", "rmw_zenoh"], default="bridge")
    ap.add_argument("--domain-id", type=int, default=0)
    ap.add_argument("--namespace", default="")
    ap.add_argument("--profile", choices=sorted(PROFILES), default="generic")
    ap.add_argument("--profile-overrides", default="{}", help="JSON object of profile fields")
    ap.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to")
    ap.add_argument("--listen", action="append", default=[], help="zenoh endpoint to listen on")
    ap.add_argument("--mode", choices=["peer", "client"], default=None, help="zenoh mode (default: the environment's)")
    ap.add_argument("--username", default=None, help="usrpwd user at an authenticated router (ros2_robot)")
    ap.add_argument("--password-file", default=None, help="a file holding that user's password")
    ap.add_argument("--config", default="{}", help="JSON object of StandInConfig fields (time_scale, latency_s, ...)")
    ap.add_argument("--time-scale", type=float, default=None)
    args = ap.parse_args(argv)
    configure_logging("ros2_robot", "local", "INFO")
    cfg = json.loads(args.config)
    cfg["scene"] = args.scene
    if args.scenes_dir:
        cfg["scenes_dir"] = args.scenes_dir
    if args.time_scale is not None:
        cfg["time_scale"] = args.time_scale
    config = StandInConfig.model_validate(cfg)
    prof = profile(args.profile, json.loads(args.profile_overrides))
    transport = ZenohRos2Transport(ZenohTransportConfig(zenoh=bus_settings(args)))
    keys = key_style(args.keys, domain_id=args.domain_id, namespace=args.namespace)
    robot = StandInRobot(config, prof, transport, keys)
    freeze_started_heap()
    stop = threading.Event()

    def on_signal(*_):
        robot.stop()
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    log.info("stand-in robot up: scene %s, profile %s, keys %s, time scale %.1f, pose %s",
             args.scene, args.profile, args.keys, config.time_scale, robot.true_pose.position_m)
    print(f"ros2 stand-in ready (keys {args.keys}, profile {args.profile})", flush=True)
    try:
        robot.run()
    finally:
        robot.close()
        transport.close()
        log.info("stopped after %d ticks, %d commands, %d collisions; Nav2 goals: %s", robot.stats.ticks,
                 robot.stats.cmd_received, robot.stats.collisions,
                 ", ".join(f"{k} {v}" for k, v in sorted(robot.stats.nav2_goals.items())) or "none")
        # Only the stand-in knows the truth: what its odometry had drifted by the end (a drifting run's figure).
        dx, dy, dyaw = robot.odometry_error()
        log.info("odometry off the true pose at the end: %.3f m, %.2f deg", math.hypot(dx, dy), abs(math.degrees(dyaw)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
