"""Simulators of the generated houses, built once per test session (the world library's, robot-io's and
the services' unit tests share them)."""

from __future__ import annotations

import os
import sys

# One math-library thread per core an xdist worker has: ``make test-unit`` runs two workers on two
# cores, and torch's OpenMP team of two (OpenBLAS's too) then shares its core with the other worker.
# OpenMP threads spin while they wait at each barrier, so a descheduled team member turns every parallel
# op into busy-waiting: test_renderer_visibility.py's torch tests took 38.5 s of CPU beside one busy
# core and 13.3 s with one thread, the same images. Only in a worker (the controller's environment is
# every worker's), before torch loads (it reads it once); an OMP_NUM_THREADS of the caller's wins, and a
# torch loaded earlier (a whole-tree run) is told too. A serial run keeps every core's thread.
if "PYTEST_XDIST_WORKER" in os.environ:
    _workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    _threads = int(os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // _workers))))
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(_threads)

import pytest  # noqa: E402

from services.robot_io.core.robot import SimConfig, SimRobot  # noqa: E402


@pytest.fixture(scope="session")
def house_robot() -> SimRobot:
    return SimRobot(SimConfig(scene="generated:0", camera={"width_px": 64, "height_px": 64}))


@pytest.fixture(scope="session")
def two_floor_robot() -> SimRobot:
    return SimRobot(SimConfig(scene="generated:1:floors=2:area=160", camera={"width_px": 64, "height_px": 64}))
