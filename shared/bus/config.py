"""The one place that builds a ``zenoh.Config`` (the zenoh-python examples' common.py).

Tests, the launcher, the router and every service call :func:`zenoh_config`; nobody else calls
``insert_json5``.
"""

from __future__ import annotations

import json
import os
from typing import Literal

from pydantic import BaseModel, Field, SecretStr


class ZenohSettings(BaseModel):
    """How a process joins the bus. ``ANT_ZENOH__MODE=client`` etc. from the environment."""

    mode: Literal["peer", "client", "router"] = "peer"
    connect: list[str] = Field(default_factory=list, description="endpoints, e.g. tcp/127.0.0.1:7447")
    listen: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False  # off by default: explicit endpoints are predictable and test-safe
    username: str | None = Field(None, description="usrpwd login at the router (with an ACL: the service name)")
    password: SecretStr | None = Field(None, description="usrpwd password (ANT_ZENOH__PASSWORD)")
    password_file: str | None = Field(None, description="a file holding the password (ANT_ZENOH__PASSWORD_FILE): "
                                                        "what a container gets from a secrets volume")
    config_file: str | None = Field(
        default_factory=lambda: os.environ.get("ZENOH_CONFIG") or None,
        description="a zenoh JSON5 config file (ZENOH_CONFIG); the fields above override it",
    )


def zenoh_config(settings: ZenohSettings):
    import zenoh

    conf = zenoh.Config.from_file(settings.config_file) if settings.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    if settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    password = settings.password.get_secret_value() if settings.password else None
    if password is None and settings.password_file:
        with open(settings.password_file) as f:
            password = f.read().strip()
    if settings.username and password:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(settings.username))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return conf
