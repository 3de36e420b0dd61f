"""Helpers of the contract tests: waiting, and a real router with the generated ACL on 127.0.0.1."""

from __future__ import annotations

import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from deploy.launcher import free_port
from deploy.zenoh import acl
from shared.bus.config import ZenohSettings
from shared.bus.zenoh_bus import ZenohBus
from tests.waiting import wait_until

__all__ = ["AuthRouter", "authenticated_router", "wait_until"]  # the two-peer fixture ``peers`` is in tests/conftest.py


class AuthRouter:
    """A running authenticated router; ``connect`` joins it as one user, in client mode."""

    def __init__(self, tmp: Path, endpoint: str, passwords: Mapping[str, str]):
        self.tmp, self.endpoint, self.passwords = tmp, endpoint, passwords

    def connect(self, user: str, password: str | None = None) -> ZenohBus:
        path = self.tmp / f"{user}-{password or 'ok'}.json5"
        path.write_text(acl.render(acl.client_config(user, password or self.passwords[user], [self.endpoint])))
        return ZenohBus(ZenohSettings(mode="client", connect=[self.endpoint], config_file=str(path)))


@contextmanager
def authenticated_router(tmp: Path, passwords: Mapping[str, str], **config: Any) -> Iterator[AuthRouter]:
    """A router on a free loopback port with usrpwd for ``passwords`` and the ACL of
    ``acl.router_config(**config)``, as the launcher and compose run it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    users = tmp / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
    router_file = tmp / "router.json5"
    router_file.write_text(acl.render(acl.router_config([endpoint], users_file=str(users), **config)))
    router = ZenohBus(ZenohSettings(mode="router", listen=[endpoint], config_file=str(router_file)))
    try:
        yield AuthRouter(tmp, endpoint, passwords)
    finally:
        router.close()


class Inbox:
    """A subscriber's callback that keeps every (key, payload) it got, for tests that wait on deliveries."""

    def __init__(self):
        self.got: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()

    def __call__(self, key, data):
        with self.lock:
            self.got.append((key, bytes(data)))

    def has(self, key, data=None):
        with self.lock:
            return any(k == key and (data is None or d == data) for k, d in self.got)
