"""Bus credentials, generated at first start and never committed: one zenoh ``usrpwd`` user per service
(its name is the service name, the ACL's subject) plus read-only ``operator`` users for tools and tests,
the robot's ROS 2 side (``ros2_robot``: the stand-in, or a real robot's zenoh-bridge-ros2dds / rmw_zenoh
router, allowed its ROS 2 key space only) and the router configuration with the generated ACL
(:mod:`deploy.zenoh.acl`).

    python -m deploy.credentials --dir /creds        # compose's init container; idempotent

Writes into ``--dir`` (created 0700): ``users.txt`` (the router's dictionary, 0600), one
``<user>.password`` per user (0600, what ``ANT_ZENOH__PASSWORD_FILE`` points at) and ``router.json5``
(the authenticated router with the ACL). An existing ``users.txt`` is kept: credentials are made once.
"""

from __future__ import annotations

import argparse
import os
import secrets
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

from deploy.zenoh import acl

READERS = ("operator",)


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def read_users(path: Path) -> dict[str, str]:
    users = {}
    for line in path.read_text().splitlines():
        if line.strip() and ":" in line:
            user, _, password = line.partition(":")
            users[user] = password
    return users


def ensure_credentials(directory: Path | str, *, listen: Sequence[str] = ("tcp/[::]:7447",),
                       users_file: str | None = None, instances: Mapping[str, Sequence[str]] | None = None,
                       services: Sequence[str] = acl.SERVICES, readers: Sequence[str] = READERS,
                       ros2: acl.Ros2Side | None = None) -> dict[str, str]:
    """Create (once) or read the credentials in ``directory``; (re)write the router config; returns
    user -> password. ``users_file`` is where the router will see ``users.txt`` (a mount point).
    ``ros2``: the ROS 2 side's user and key space (default: every built-in profile, both key styles)."""
    ros2 = ros2 or acl.Ros2Side()
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True, mode=0o700)
    users_path = d / "users.txt"
    if users_path.exists():
        users = read_users(users_path)
    else:
        users = {}
    missing = [u for u in (*services, *readers, ros2.user) if u not in users]
    if missing:
        users.update({u: secrets.token_urlsafe(24) for u in missing})
        _write_private(users_path, "".join(f"{u}:{p}\n" for u, p in users.items()))
    for user, password in users.items():
        _write_private(d / f"{user}.password", password + "\n")
    conf = acl.router_config(list(listen), users_file=users_file or str(users_path), instances=instances,
                             readers=readers, ros2=ros2)
    (d / "router.json5").write_text(acl.render(conf, header="generated at first start by deploy/credentials.py"))
    return users


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", default="/creds")
    ap.add_argument("--users-file", default="/etc/zenoh/creds/users.txt", help="users.txt as the router sees it")
    ap.add_argument("--instances", action="append", default=[], help="service=inst1,inst2 (instance routes)")
    ap.add_argument("--ros2-keys", action="append", choices=sorted(acl.ROS2_KEY_STYLES), default=[],
                    help="the key style(s) the robot's ROS 2 side speaks (default: both)")
    ap.add_argument("--ros2-domain-id", type=int, default=0, help="the robot's ROS_DOMAIN_ID (rmw_zenoh keys)")
    ap.add_argument("--ros2-namespace", default="", help="the robot's ROS namespace")
    ap.add_argument("--ros2-prefix", default="", help="zenoh-bridge-ros2dds's namespace option (bridge keys)")
    ap.add_argument("--ros2-name", action="append", default=[],
                    help="a ROS topic/service beyond the built-in profiles' (a generic profile's overrides)")
    args = ap.parse_args(argv)
    ros2 = acl.Ros2Side(styles=tuple(args.ros2_keys) or acl.Ros2Side.styles,
                        names=tuple(dict.fromkeys([*acl.default_ros_names(), *args.ros2_name])),
                        domain_id=args.ros2_domain_id, namespace=args.ros2_namespace, prefix=args.ros2_prefix)
    users = ensure_credentials(args.dir, users_file=args.users_file, instances=acl.parse_instances(args.instances),
                               ros2=ros2)
    print(f"bus credentials for {len(users)} users in {args.dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
