"""Shared fixtures: the reference data beside the repo (skipped when absent), two real zenoh peers."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# One math-library thread per core an xdist worker has: ``make test-unit`` runs two workers on two
# cores, and torch's OpenMP team of two (OpenBLAS's too) then shares its core with the other worker.
# OpenMP threads spin while they wait at each barrier, so a descheduled team member turns every parallel
# op into busy-waiting: test_renderer_visibility.py's torch tests took 38.5 s of CPU beside one busy
# core and 13.3 s with one thread, the same images. Only in a worker (the controller's environment is
# every worker's), here in the root conftest, before any tier's test module loads numpy or torch (each
# reads it once); an OMP_NUM_THREADS of the caller's wins. A serial run keeps every core's thread.
if "PYTEST_XDIST_WORKER" in os.environ:
    _workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    _threads = int(os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // _workers))))
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(_threads)

import pytest  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
# ANT_SHARED_DATA: the data from a checkout that is not beside it (a git worktree elsewhere).
SHARED_DATA = Path(os.environ.get("ANT_SHARED_DATA") or REPO_ROOT.parent / "shared" / "data")


# Under pytest-xdist (``make test``: ``-n 2 --dist loadgroup``) a worker runs whole groups, and builds a
# session fixture once per worker that uses it. A group is one file, so a module-scoped fixture (a ROS 2
# stand-in, a server) is built once. The files that use one of these costly session fixtures share its group
# instead, so one worker builds it (a file's group: the first of them that any of its tests uses, in this
# order). The launched system is here too: the tests that use it run one after another on one worker, while
# the other worker runs the `system` tests that start processes of their own (``make test``'s second run).
SHARED_FIXTURE_GROUPS = {  # "<the directory of its conftest.py>::<fixture>": group
    "tests::system": "system",  # the launched OS processes (tests/launched.py)
    "tests/reliability::live": "live",  # the reliability suite's in-process system (a router and every service)
    "tests/unit/reconstructor::house": "toured-house",  # the reconstructor tests' explored and toured house
    "tests/unit/renderer::room_mesh": "built-flat",  # the renderer tests' flat, its 1e6-point cloud and index
    "tests/unit::house_robot": "sim-houses",  # tests/unit's two simulated houses
    "tests/unit::two_floor_robot": "sim-houses",
    "tests/unit/mapper::rooms_discovery": "rooms-discovery",  # the box-room world explored (mapper tests)
}
_RANK = {g: i for i, g in enumerate(dict.fromkeys(SHARED_FIXTURE_GROUPS.values()))}


# The work units xdist hands out before all others, in this order. It hands them out largest first by
# test count, and a worker asks for another when two or fewer of its tests are left, so a long unit of
# few tests starts late: in the system tier (``make test``'s second run) the ROS 2 demo (one test, ~50 s,
# mostly robot time) started at 68 s on one worker, which ended at 122 s, while the other, done with the
# launched system's tests (~95 s), had nothing left at 95 s. The longest units first (each worker starts
# with two: the system's tests on one, the demo and the flaky link's ~18 s on the other), then the rest
# where a worker is free. Units a run does not have (the in-process tier's) change nothing.
FIRST_UNITS = ("system", "tests/e2e/test_ros2_demo.py", "tests/reliability/test_ros2_flaky_link.py")


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup`` with :data:`FIRST_UNITS` at the head of its queue; None (xdist's own
    choice) for any other mode."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class LongestFirst(LoadGroupScheduling):
        def _assign_work_unit(self, node) -> None:
            for unit in reversed(FIRST_UNITS):  # the queue is ordered: move these to its head
                if unit in self.workqueue:
                    self.workqueue.move_to_end(unit, last=False)
            super()._assign_work_unit(node)

    return LongestFirst(config, log)


@pytest.hookimpl(tryfirst=True)
def pytest_collection(session) -> None:
    """On an xdist worker: pytest's assertion rewriting of this worker's share of the test modules that
    have no rewritten bytecode yet, before it collects (see :func:`_rewrite_share`)."""
    worker, count = os.environ.get("PYTEST_XDIST_WORKER", ""), os.environ.get("PYTEST_XDIST_WORKER_COUNT", "")
    if worker.startswith("gw") and worker[2:].isdigit() and count.isdigit() and int(count) > 1:
        _rewrite_share(session, int(worker[2:]), int(count))


def _rewrite_share(session, index: int, count: int) -> None:
    """Every xdist worker collects every test module, and in a fresh clone (no ``__pycache__``) each one
    rewrote all their asserts: ``tests/unit``'s 126 modules are 3.8 s of CPU of a worker's cold 8.8 s
    collection (4.7 s with the rewritten bytecode present), done once per worker. Here each worker first
    writes its share (modules dealt largest first, round robin) as pytest's own import hook would: the
    same functions, the same atomic write of the same file. When it then collects, the others' shares
    are written too, or being written: one not yet there is rewritten by whichever worker gets to it
    first, as before, so nothing waits and the modules' code is the same. With the bytecode present
    (a warm run) this is a stat per module. These are pytest's internals: a pytest that moved them
    loses the speed-up, never a test (the ImportError below)."""
    if sys.dont_write_bytecode or session.config.getoption("assertmode") != "rewrite":
        return
    try:
        from _pytest.assertion.rewrite import (PYC_TAIL, _rewrite_test, _write_pyc, assertstate_key,
                                               get_cache_dir, try_makedirs)
    except ImportError:  # pragma: no cover - another pytest
        return
    files: set[Path] = set()
    for arg in session.config.args:
        root = Path(arg.split("::", 1)[0]).resolve()
        if root.is_dir():
            files.update(f for pat in ("test_*.py", "conftest.py") for f in root.rglob(pat))
    state = session.config.stash[assertstate_key]
    share = sorted(files, key=lambda f: (-f.stat().st_size, str(f)))[index::count]
    for fn in share:
        pyc = get_cache_dir(fn) / (fn.name[:-3] + PYC_TAIL)
        if pyc.exists() or not try_makedirs(pyc.parent):
            continue
        source_hash, co = _rewrite_test(fn, session.config)
        _write_pyc(state, co, source_hash, pyc)


def _shared_fixtures(item) -> set[str]:
    """The test's fixtures (those it asks for and theirs), each as ``<conftest directory>::<name>``."""
    defs = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {})
    return {f"{d[-1].baseid}::{name}" for name, d in defs.items() if d}


def _file_groups(items) -> dict[str, str]:
    """Each test file's xdist group (above)."""
    groups: dict[str, str] = {}
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        groups.setdefault(path, path)
        for fixture in _shared_fixtures(item) & SHARED_FIXTURE_GROUPS.keys():
            group = SHARED_FIXTURE_GROUPS[fixture]
            if groups[path] not in _RANK or _RANK[group] < _RANK[groups[path]]:
                groups[path] = group
    return groups


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook turns the xdist_group marks into node id suffixes
def pytest_collection_modifyitems(config, items):
    """A test that uses the launched system (the ``system`` fixture below: a router and every
    service as OS processes) is a ``system`` test wherever it lives, so ``-m "not system"`` keeps a tier
    in-process without each file having to say so. Every test also gets its xdist group (above); without
    ``--dist loadgroup`` the mark changes nothing."""
    for item in items:
        if "system" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.system)
    # The tests that move the launched system's robots to other scenes (``system_on_scene``) run after every
    # test that uses the system as the fixture made it: the first of those used to find both robots moved
    # and reload the shared house on each (``put_back``: the default house and its nav grids, seconds of CPU
    # on the tier's longest worker). A stable sort: every other test keeps its place.
    items.sort(key=lambda item: "system_on_scene" in getattr(item, "fixturenames", ()))
    groups = _file_groups(items)
    for item in items:
        group = groups[item.nodeid.split("::", 1)[0]]
        item.add_marker(pytest.mark.xdist_group(group))
        if getattr(config.option, "loadgroup", False):  # set on an xdist worker under --dist loadgroup
            _suffix_group(item, group)


def pytest_collection_finish(session) -> None:
    """Everything collection left alive (the imported modules of numpy, torch, scipy, pydantic, the
    product and the test modules: ~all of a worker's objects) moves out of the cyclic garbage
    collector's reach (``gc.freeze``). Each full collection otherwise walks all of it again, and the
    tests' allocations trigger one every few seconds: tests/unit/{evaluation,gateway,planner} spent
    3.2 s of 38.7 s of CPU in full collections, 2.1 s with them frozen. Only collection is skipped:
    frozen objects that become garbage are still freed by reference counting, none of them is a test's."""
    import gc

    gc.freeze()


def _suffix_group(item, group: str) -> None:
    """The ``@group`` node id suffix that xdist's scheduler groups by, written where pytest reads it.

    pytest-xdist 3.8 writes it to ``item._nodeid``, which pytest 9 no longer reads (a node's id is the
    ``NodeId`` in ``item._id``): the marks were ignored, every test was its own unit, and the two workers
    each built the costly session fixtures and the module fixtures of files whose tests they shared
    (tests/unit/mapper/test_sim_end_to_end.py's 200 m2 exploration twice, one per worker). This is xdist's own
    suffix (``<node id>@<group>``), so its scheduler and reports read it as with an older pytest."""
    if hasattr(item, "_id") and "@" not in item.nodeid.rpartition("]")[2]:
        from _pytest.nodeid import NodeId

        item._id = NodeId.parse(f"{item.nodeid}@{group}")


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
    behind: afterwards nothing is running, and the robots are put back on the shared scene before the next
    test that uses ``system`` itself (below), not after each of these tests (they run one after another:
    each switches its robots away again, and a reload of the shared house costs seconds)."""
    from tests.launched import cancel_left_running

    yield system
    cancel_left_running(system)


@pytest.fixture(autouse=True)
def _system_on_its_scene(request):
    """A test that uses ``system`` (not ``system_on_scene``) finds every robot on the shared scene."""
    if "system" in request.fixturenames and "system_on_scene" not in request.fixturenames:
        from tests.launched import put_back

        put_back(request.getfixturevalue("system"))


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
