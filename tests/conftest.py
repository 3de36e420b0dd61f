"""Shared fixtures: the reference data beside the repo (skipped when absent), two real zenoh peers."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
# ANT_SHARED_DATA: the data from a checkout that is not beside it (a git worktree elsewhere).
SHARED_DATA = Path(os.environ.get("ANT_SHARED_DATA") or REPO_ROOT.parent / "shared" / "data")


# Under pytest-xdist (``make test``: ``-n 2 --dist loadgroup``) a worker runs whole groups, and a group is
# built once per worker that runs any of it. By default a group is one file, so a module-scoped fixture (a
# ROS 2 stand-in, a server) is never built twice; these session fixtures are costly enough that every test
# using one shares a group, so one worker builds it: the first fixture a test uses in this table wins.
SHARED_FIXTURE_GROUPS = {
    "system": "system",  # the launched OS processes: one set, their tests one after another, as when serial
    "live": "live",  # the reliability suite's in-process system (a router and every service)
}


def _xdist_group(item) -> str:
    names = getattr(item, "fixturenames", ())
    for fixture, group in SHARED_FIXTURE_GROUPS.items():
        if fixture in names:
            return group
    if item.get_closest_marker("system"):  # starts OS processes: one after another, as in a serial run
        return "system"
    return item.nodeid.split("::", 1)[0]


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook turns the xdist_group marks into node id suffixes
def pytest_collection_modifyitems(config, items):
    """A test that uses the launched system (the ``system`` fixture below: a router and every
    service as OS processes) is a ``system`` test wherever it lives, so ``-m "not system"`` keeps a tier
    in-process without each file having to say so. Every test also gets its xdist group (above); without
    ``--dist loadgroup`` the mark changes nothing."""
    for item in items:
        if "system" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.system)
        item.add_marker(pytest.mark.xdist_group(_xdist_group(item)))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repo; tests that use it skip on a user's fresh clone."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"reference data not present at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def system(tmp_path_factory):
    """The whole system as real processes over a real zenoh router, supervised (restart on crash), two
    robots, with one map imported from the scene (tests/launched.py); started once per session and shared
    by tests/e2e and tests/reliability."""
    from tests.launched import import_map, launch

    with launch(tmp_path_factory.mktemp("system")) as launcher:
        import_map(launcher)
        yield launcher


@pytest.fixture
def system_on_scene(system):
    """``system`` for a test that switches its robots' scenes (the evaluation runner does) or leaves work
    behind: afterwards every robot is back on the shared scene with nothing running."""
    from tests.launched import put_back

    yield system
    put_back(system)


@pytest.fixture
def peers():
    """Two real zenoh peers in one process on loopback (a free port, multicast off); connected once a
    token declared on one is visible from the other."""
    from deploy.launcher import free_port
    from shared.bus.config import ZenohSettings
    from shared.bus.zenoh_bus import ZenohBus
    from tests.waiting import wait_until

    port = free_port()
    a = ZenohBus(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]))
    b = ZenohBus(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))
    tok = a.liveliness_token("ant/alive/test/ready")
    wait_until(lambda: b.alive("ant/alive/test/ready", timeout_s=0.5), what="peers connected")
    tok.close()
    yield a, b
    b.close()
    a.close()
