"""Every launcher leaves no process behind: SIGINT, SIGTERM and SIGHUP stop every child, and a launcher
killed by SIGKILL takes its children with it (deploy.launcher's one lifecycle).

Each case starts a real launcher program (``deploy.demo``, ``deploy.up``, the evaluation CLI, a bench)
as a person would, waits until it has spawned its router and services, sends one signal, and then looks
for any process that still carries the case's marker in its environment (every child inherits the
launcher's environment, so this also finds a child restarted by the supervisor, or a grandchild).
The signal comes while the services are still starting (the cheapest moment, and the one with the most
half-done state); one case signals the demo once its system is up, the path issue 31 found orphans on.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from deploy.launcher import SERVICES, free_port
from tests.waiting import wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.system]
ROOT = Path(__file__).resolve().parents[2]
SMALL_SCENE = "generated:3:area=50"
MARKER = "ANT_TEST_LAUNCHER_CASE"
SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGKILL]


def _environ(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:  # gone, or another user's
        return b""


def _alive(pid: int) -> bool:
    """Running (a zombie has ended: it only waits for its new parent to reap it)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def marked(case: str, exclude: int) -> list[int]:
    """Live processes started for this case (other than the launcher itself)."""
    needle = f"{MARKER}={case}".encode() + b"\0"
    pids = [int(p) for p in os.listdir("/proc") if p.isdigit() and int(p) != exclude]
    return [pid for pid in pids if needle in _environ(pid) and _alive(pid)]


@pytest.fixture(scope="module")
def episodes(tmp_path_factory) -> Path:
    from evaluation.dataset import SetSpec, generate_set, write_set

    ds, gt = generate_set(SetSpec(houses=1, per_house=1, floors=(1,), seed=7, area_m2=60.0), with_gt=True)
    return write_set(ds, gt, tmp_path_factory.mktemp("set") / "set.json.gz")[0]


def launcher_argv(name: str, run_dir: Path, episodes: Path) -> tuple[list[str], int]:
    """The program and how many children it starts (router + services)."""
    py = sys.executable
    if name == "demo":
        return [py, "-m", "deploy.demo", "--run-dir", str(run_dir), "--scene", SMALL_SCENE, "--max-steps", "20",
                "--mission-steps", "3"], 1 + len(SERVICES)
    if name == "up":
        return [py, "-m", "deploy.up", "--port", str(free_port()), "--run-dir", str(run_dir), "--scene",
                SMALL_SCENE], 1 + len(SERVICES)
    if name == "evaluation":
        return [py, "-m", "evaluation", "run", "--episodes", str(episodes), "--out", str(run_dir), "--policy",
                "oracle", "--map-source", "curated", "--max-steps", "3", "--no-progress"], 1 + len(SERVICES)
    if name == "bench":
        # The renderer-replica bench starts its own router and renderer through the same launcher.
        return [py, "-m", "bench.replicas", "--requests", "2", "--latency-requests", "2"], 2
    raise AssertionError(name)


class Case:
    """One launcher program given one signal."""

    def __init__(self, name: str, sig: signal.Signals, tmp_path: Path, episodes: Path):
        self.name, self.sig, self.case = name, sig, uuid.uuid4().hex
        self.argv, self.children = launcher_argv(name, tmp_path / f"{name}-{sig.name}", episodes)
        self.env = {**os.environ, MARKER: self.case, "TMPDIR": str(tmp_path), "ANT_LOG_LEVEL": "WARNING",
                    "ANT_ROBOT_CONFIG": f'{{"scene": "{SMALL_SCENE}"}}'}
        self.env.pop("ANT_API_TOKEN", None)
        self.out_path = tmp_path / f"{name}-{sig.name}.out"
        self.proc: subprocess.Popen | None = None

    def output(self) -> str:
        return self.out_path.read_text(errors="replace")

    def start(self) -> None:
        with open(self.out_path, "wb") as out:
            self.proc = subprocess.Popen(self.argv, cwd=ROOT, env=self.env, stdout=out, stderr=subprocess.STDOUT)

    def marked(self) -> list[int]:
        return marked(self.case, self.proc.pid)

    def wait_spawned(self, when_up: bool = False) -> None:
        """Until the launcher has started its router and every service (``when_up``: and they are alive)."""
        proc = self.proc
        try:
            wait_until(lambda: len(self.marked()) >= self.children or proc.poll() is not None, 180,
                       f"{self.name} spawns its {self.children} processes", interval_s=0.1)
            if when_up:
                wait_until(lambda: "all services alive" in self.output() or proc.poll() is not None, 300,
                           f"{self.name}'s system is up", interval_s=0.2)
        except TimeoutError as exc:
            raise AssertionError(f"{exc}; output:\n{self.output()}") from None
        assert proc.poll() is None, f"{self.name} ended before the signal ({proc.returncode}):\n{self.output()}"
        # Counted again, and waited for: a short-lived helper process that inherits the marker (a library
        # shelling out while a service starts) can make up the count for a moment and then be gone, and
        # the signal must not come before every child the launcher starts is there.
        try:
            wait_until(lambda: len(self.marked()) >= self.children, 180,
                       f"{self.name}'s {self.children} processes all alive at once", interval_s=0.1)
        except TimeoutError as exc:
            raise AssertionError(f"{exc}; output:\n{self.output()}") from None

    def check_stopped(self) -> None:
        """The launcher ends, and every process it started with it, in bounded time."""
        name, sig = self.name, self.sig
        try:
            code = self.proc.wait(90)  # the launcher's own stop: SIGTERM, then SIGKILL after 20 s per group
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{name} did not end within 90 s of {sig.name}:\n{self.output()}") from None
        try:
            wait_until(lambda: not self.marked(), 30, f"every process of {name} ends", interval_s=0.1)
        except TimeoutError:
            left = {pid: Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")[:120]
                    for pid in self.marked()}
            raise AssertionError(f"{sig.name} to {name} left {len(left)} processes: {left}\n{self.output()}") from None
        if sig == signal.SIGKILL:
            assert code == -signal.SIGKILL
        elif name in ("demo", "evaluation"):
            assert code == 128 + sig, self.output()  # the shell's "ended by signal N"
        elif name == "up":
            assert code == 0 and "stopped every process" in self.output(), self.output()

    def cleanup(self) -> None:
        """Nothing outlives the test, even a failed one."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        for pid in marked(self.case, -1):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.parametrize("name", ["demo", "up", "evaluation", "bench"])
def test_each_signal_to_a_starting_launcher_leaves_no_process(name, tmp_path, episodes):
    # The four signals' cases run side by side (four launchers at once), which bounds the test's time by
    # the slowest case rather than their sum; each case has its own marker, so they cannot mix. Each case
    # gets its signal as soon as all its processes are there: waiting for the other cases' too only let its
    # services import on (CPU the 2-core machine shares with the other cases), and they are no less started.
    cases = [Case(name, sig, tmp_path, episodes) for sig in SIGNALS]
    try:
        for c in cases:
            c.start()
        for c in cases:
            c.wait_spawned()
            c.proc.send_signal(c.sig)
        for c in cases:
            c.check_stopped()
    finally:
        for c in cases:
            c.cleanup()


def test_sigterm_to_a_running_demo_leaves_no_process(tmp_path, episodes):
    """Issue 31's case: a SIGTERM (a CI timeout, kill, systemd, docker stop) to a demo whose system is up."""
    case = Case("demo", signal.SIGTERM, tmp_path, episodes)
    try:
        case.start()
        case.wait_spawned(when_up=True)
        case.proc.send_signal(signal.SIGTERM)
        case.check_stopped()
    finally:
        case.cleanup()
