"""The default docker-compose.yml is authenticated, checked without docker (issue 15 item 4).

* Wiring: every service that speaks zenoh joins in client mode as its own user, with the password
  file the ``credentials`` init container writes, mounts that volume, and starts only after the router,
  which itself waits for the credentials and reads the router config they generated.
* Behaviour: ``deploy.credentials`` is run with the compose command's own arguments (its paths moved
  into a temp dir), and a real zenoh router process is started on the config it wrote, as the launcher
  starts it (``python -m deploy.router --config``). A client without credentials is refused; each
  compose service's settings, built from its compose environment, get in. What each user may then do
  is tests/contract/test_acl.py's subject.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from deploy import credentials
from deploy.launcher import free_port, wait_tcp
from deploy.zenoh import acl
from shared.bus.config import ZenohSettings, zenoh_config

REPO = Path(__file__).resolve().parents[2]
COMPOSE = yaml.safe_load((REPO / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]
CREDS_MOUNT = "/creds"
# The module each generated user runs: a service as itself, the ROS 2 side as the stand-in robot.
MODULE_OF_USER = {**{svc: f"services.{svc}" for svc in acl.SERVICES},
                  acl.Ros2Side.user: "services.robot_io.tools.ros2_robot"}


def zenoh_services() -> dict[str, dict]:
    """Every compose service that joins the bus (it connects to the router)."""
    return {name: s for name, s in SERVICES.items() if "ANT_ZENOH__CONNECT" in (s.get("environment") or {})}


def test_every_zenoh_service_joins_as_its_own_user_with_the_generated_password():
    services = zenoh_services()
    assert {"robot_io", "mapper", "reconstructor", "renderer", "planner", "gateway", "reconstructor-gpu",
            "renderer-gpu", "planner-gpu", "ros2-robot"} <= services.keys()
    for name, s in services.items():
        env = s["environment"]
        user = env.get("ANT_ZENOH__USERNAME")
        module = s["command"][s["command"].index("-m") + 1]  # python -m <module> ...
        assert user in MODULE_OF_USER and module == MODULE_OF_USER[user], (name, user, module)
        assert env["ANT_ZENOH__PASSWORD_FILE"] == f"{CREDS_MOUNT}/{user}.password", name
        assert env["ANT_ZENOH__MODE"].endswith(":-client}"), (name, "client mode: the router's ACL applies")
        mounts = [v for v in s.get("volumes", [])]
        assert f"creds:{CREDS_MOUNT}:ro" in mounts, (name, mounts)
        assert s["depends_on"]["router"]["condition"] == "service_healthy", name


def test_the_router_waits_for_the_credentials_and_reads_what_they_wrote():
    creds, router = SERVICES["credentials"], SERVICES["router"]
    assert router["depends_on"]["credentials"]["condition"] == "service_completed_successfully"
    args = creds["command"]
    assert args[:3] == ["python", "-m", "deploy.credentials"]
    out_dir = args[args.index("--dir") + 1]
    users_file = args[args.index("--users-file") + 1]
    assert f"creds:{out_dir}" in creds["volumes"]
    # The router mounts the same volume where the generated config says the users file is.
    router_mount = next(v.split(":")[1] for v in router["volumes"] if v.startswith("creds:"))
    assert users_file == f"{router_mount}/users.txt"
    config = router["command"][router["command"].index("-c") + 1]
    assert config == f"${{ZENOH_ROUTER_CONFIG:-{router_mount}/router.json5}}"
    assert "volumes" in COMPOSE and "creds" in COMPOSE["volumes"]


@pytest.fixture(scope="module")
def compose_router(tmp_path_factory):
    """deploy.credentials run as compose runs it (paths inside a temp dir), and a router process on
    the config it wrote, started as the launcher starts one."""
    tmp = tmp_path_factory.mktemp("compose-auth")
    args = SERVICES["credentials"]["command"][3:]
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    mapped = [str(tmp / a.lstrip("/")) if a.startswith("/") else a for a in args]
    assert credentials.main(mapped) == 0
    out_dir = Path(mapped[mapped.index("--dir") + 1])
    users_file = Path(mapped[mapped.index("--users-file") + 1])
    # compose mounts the volume at two places; here it is one directory, so the users file must be there.
    users_file.parent.mkdir(parents=True, exist_ok=True)
    users_file.write_text((out_dir / "users.txt").read_text())
    config = (out_dir / "router.json5").read_text()
    parsed = json.loads(config.split("\n", 1)[1] if config.startswith("//") else config)
    # Listen on a free loopback port instead of the container's 7447, as the launcher does.
    parsed["listen"] = {"endpoints": [endpoint]}
    router_file = tmp / "router.json5"
    router_file.write_text(json.dumps(parsed))
    proc = subprocess.Popen([sys.executable, "-m", "deploy.router", "--listen", endpoint, "--config", str(router_file)],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_tcp(port, 20.0)
        yield endpoint, out_dir, parsed
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.mark.system  # the router as its own process
def test_the_generated_router_config_requires_usrpwd_and_enables_the_acl(compose_router):
    _, _, parsed = compose_router
    assert parsed["transport"]["auth"]["usrpwd"]["dictionary_file"]
    assert parsed["access_control"]["enabled"] is True
    assert parsed["access_control"]["default_permission"] == "deny"


def _settings(env: dict[str, str], endpoint: str, creds_dir: Path) -> ZenohSettings:
    """The ZenohSettings a compose service builds from its environment (ANT_ZENOH__*), with the
    container's /creds moved to where the credentials were generated and the router on loopback."""
    fields = {k.removeprefix("ANT_ZENOH__").lower(): v for k, v in env.items() if k.startswith("ANT_ZENOH__")}
    return ZenohSettings(mode="client", connect=[endpoint], multicast_scouting=False,
                         username=fields["username"],
                         password_file=fields["password_file"].replace(CREDS_MOUNT, str(creds_dir), 1))


@pytest.mark.system  # the router as its own process
def test_the_router_refuses_a_client_without_credentials_and_admits_every_compose_service(compose_router):
    import zenoh

    endpoint, creds_dir, _ = compose_router
    with pytest.raises(Exception, match="(?i)unable to connect"):
        zenoh.open(zenoh_config(ZenohSettings(mode="client", connect=[endpoint], multicast_scouting=False)))
    users = {s["environment"]["ANT_ZENOH__USERNAME"]: s["environment"] for s in zenoh_services().values()}
    for user, env in sorted(users.items()):
        conf = zenoh_config(_settings(env, endpoint, creds_dir))
        assert json.loads(conf.get_json("transport/auth/usrpwd/user")) == user
        session = zenoh.open(conf)  # raises "unable to connect" if the router refused it
        session.close()
