"""docker-compose.yml: validated by `docker compose config` when the client is here, and structurally always."""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest
import yaml

from deploy.launcher import SERVICES
from tests.conftest import REPO_ROOT

COMPOSE = REPO_ROOT / "docker-compose.yml"
GPU_SERVICES = ("reconstructor", "renderer", "planner")


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _compose_plugin() -> str | None:
    docker = shutil.which("docker")
    if not docker:
        return None
    ok = subprocess.run([docker, "compose", "version"], capture_output=True, timeout=30).returncode == 0
    return docker if ok else None


@pytest.mark.parametrize("profile", ["cpu", "gpu"])
def test_docker_compose_config_validates(profile):
    docker = _compose_plugin()
    if docker is None:
        pytest.skip("no docker client with the compose plugin on this machine (`docker compose version` fails)")
    env = {**os.environ, "RENDERERS": "2"}
    run = subprocess.run([docker, "compose", "-f", str(COMPOSE), "--profile", profile, "config", "-q"],
                         capture_output=True, text=True, timeout=60, env=env, cwd=REPO_ROOT)
    assert run.returncode == 0, run.stderr


def _variants(compose: dict, service: str) -> list[str]:
    names = [service.replace("_", "-"), service]
    return [n for n in compose["services"] if n in names or n in [f"{x}-gpu" for x in names]]


def test_every_launcher_service_has_a_container_with_a_bus_healthcheck(compose):
    for service in SERVICES:
        variants = _variants(compose, service)
        assert variants, f"{service} has no container"
        for name in variants:
            spec = compose["services"][name]
            assert spec["command"] == ["python", "-m", f"services.{service}"], name
            test = spec["healthcheck"]["test"]
            assert test[:4] == ["CMD", "python", "-m", "deploy.healthcheck"] and test[4] == service, name
            assert spec["depends_on"]["router"]["condition"] == "service_healthy", name


def test_router_is_the_pinned_official_image_with_our_config(compose):
    router = compose["services"]["router"]
    image, tag = router["image"].split(":", 1)
    assert image == "eclipse/zenoh"
    from importlib.metadata import version
    py_major_minor = ".".join(version("eclipse-zenoh").split(".")[:2])
    assert tag.startswith("${ZENOH_VERSION:-" + py_major_minor), "router image must match eclipse-zenoh python"
    assert "./deploy/zenoh/router.json5:/etc/zenoh/router.json5:ro" in router["volumes"]
    assert (REPO_ROOT / "deploy/zenoh/router.json5").is_file()
    assert "healthcheck" in router


def test_gpu_variants_reserve_an_nvidia_gpu_behind_the_gpu_profile(compose):
    for service in GPU_SERVICES:
        cpu, gpu = compose["services"][service], compose["services"][f"{service}-gpu"]
        assert cpu["profiles"] == ["cpu"] and gpu["profiles"] == ["gpu"]
        assert "deploy" not in cpu or "resources" not in cpu["deploy"]
        devices = gpu["deploy"]["resources"]["reservations"]["devices"]
        assert any(d["driver"] == "nvidia" and "gpu" in d["capabilities"] for d in devices), service
        assert cpu["command"] == gpu["command"]
    # services that are not GPU work must not be behind a profile: they run in both set-ups
    for name in ("router", "robot_io", "mapper", "gateway"):
        assert "profiles" not in compose["services"][name]


def test_state_lives_in_volumes_and_settings_come_from_the_environment(compose):
    svcs = compose["services"]
    for name in ("reconstructor", "reconstructor-gpu"):
        assert svcs[name]["environment"]["ANT_STORE_DIR"] == "/data/maps"
        assert "maps:/data/maps" in svcs[name]["volumes"]
    gw = svcs["gateway"]
    assert gw["environment"]["ANT_HOST"] == "0.0.0.0"
    assert gw["environment"]["ANT_DB_PATH"].startswith("/data/gateway/")
    assert "gateway-db:/data/gateway" in gw["volumes"]
    assert set(compose["volumes"]) >= {"maps", "gateway-db"}
    for name, spec in svcs.items():
        if name in ("router", "credentials"):
            continue
        env = spec["environment"]
        assert env["ANT_ZENOH__CONNECT"] == '["tcp/router:7447"]', name
        assert env["ANT_ZENOH__MODE"].startswith("${"), f"{name}: the zenoh mode must be overridable"


def test_gateway_waits_for_whichever_variant_runs(compose):
    deps = compose["services"]["gateway"]["depends_on"]
    for service in SERVICES:
        if service == "gateway":
            continue
        for name in _variants(compose, service):
            assert deps[name]["condition"] == "service_healthy"
            # a dependency on a variant whose profile is off must not stop the gateway from starting
            if "profiles" in compose["services"][name]:
                assert deps[name]["required"] is False


def test_renderer_replicas_come_from_the_environment(compose):
    for name in ("renderer", "renderer-gpu"):
        spec = compose["services"][name]
        assert spec["deploy"]["replicas"] == "${RENDERERS:-1}"
        # replicas need distinct instance names: the runner's hostname-pid default, not a fixed one
        assert "ANT_INSTANCE" not in spec["environment"] and "container_name" not in spec


def test_dockerfile_installs_the_lock_and_the_open3d_libraries():
    text = (REPO_ROOT / "Dockerfile").read_text()
    assert text.startswith("#") and "FROM python:3.11-slim" in text
    for lib in ("libusb-1.0-0", "libgl1", "libgomp1"):
        assert lib in text
    assert "pip install --extra-index-url" in text and "-r requirements.lock" in text
    ignored = (REPO_ROOT / ".dockerignore").read_text().split()
    assert {".venv", "runs", ".git"} <= set(ignored)


def test_the_default_compose_is_authenticated_with_generated_credentials(compose):
    """Issue 15: the bus runs usrpwd + the generated ACL by default; credentials are made at first start."""
    svcs = compose["services"]
    creds = svcs["credentials"]
    assert creds["command"][:3] == ["python", "-m", "deploy.credentials"] and "creds:/creds" in creds["volumes"]
    router = svcs["router"]
    assert "/etc/zenoh/creds/router.json5" in " ".join(router["command"])
    assert router["depends_on"]["credentials"]["condition"] == "service_completed_successfully"
    for service in SERVICES:
        for name in _variants(compose, service):
            env = svcs[name]["environment"]
            assert env["ANT_ZENOH__USERNAME"] == service, name
            assert env["ANT_ZENOH__PASSWORD_FILE"] == f"/creds/{service}.password", name
            assert "client" in env["ANT_ZENOH__MODE"], name
            assert "creds:/creds:ro" in svcs[name]["volumes"], name
    assert not list((REPO_ROOT / "deploy").rglob("*.password")) and not (REPO_ROOT / "deploy/zenoh/users.txt").exists()
    assert (REPO_ROOT / "deploy/compose.open.yml").is_file()  # the documented opt-out
