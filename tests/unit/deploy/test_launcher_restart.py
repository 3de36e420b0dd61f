"""The supervisor's restart backoff: doubling while a child keeps crashing, back to the first delay once a
restarted child has stayed up for the policy's healthy period. Real child processes, the real supervisor
loop; only the delays are short, and uptime is read from a clock the test steps."""

from __future__ import annotations

import math
import sys
import threading
import time

import pytest

from deploy.launcher import Launcher, Proc, RestartPolicy

# Crashes (exit 3) on its first three runs; on the fourth waits until the file `<runs>.release` exists, then
# exits 4; stays up from the fifth on (until the test kills it). The run count lives in a file: each run is a
# new process.
CHILD = """
import pathlib, sys, time
f = pathlib.Path(sys.argv[1]); n = int(f.read_text()) if f.exists() else 0; f.write_text(str(n + 1))
if n < 3:
    sys.exit(3)
release = f.with_suffix(".release")
while n == 3 and not release.exists():
    time.sleep(0.01)
time.sleep(0 if n == 3 else 300)
sys.exit(4)
"""


def _wait_for(cond, deadline_s: float, what: str) -> None:
    end = time.monotonic() + deadline_s
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"not within {deadline_s} s: {what}")
        time.sleep(0.01)


class StepClock:
    """Uptime as the test says: it moves only when stepped, so a crash on a loaded machine is still quick."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def test_backoff_doubles_while_crashing_and_resets_after_a_healthy_run(tmp_path):
    policy = RestartPolicy(first_backoff_s=0.05, max_backoff_s=5.0, healthy_after_s=10.0)
    launcher = Launcher(tmp_path, restart_policy=policy)
    clock = StepClock()
    runs = tmp_path / "runs"
    p = Proc("flaky", [sys.executable, "-S", "-c", CHILD, str(runs)], {}, tmp_path / "logs" / "flaky.log",
             clock=clock)
    launcher.procs.append(p)
    p.start()
    sup = threading.Thread(target=launcher._supervise, daemon=True)
    sup.start()
    try:
        # Three quick crashes: waited 0.05, 0.1, 0.2 s; the next crash would wait 0.4 s.
        _wait_for(lambda: p.restarts == 3, 30, "three restarts")
        assert p.history == [3, 3, 3] and p.next_backoff_s == pytest.approx(0.4)
        # The fourth run has started (so its start time is taken); it stays up the healthy period, then exits.
        _wait_for(lambda: runs.read_text() == "4", 30, "the fourth run")
        clock.now_s += policy.healthy_after_s
        runs.with_suffix(".release").touch()
        # Its crash waited first_backoff_s again (0.05 s, then doubled to 0.1), not 0.4 s (then 0.8).
        _wait_for(lambda: p.restarts == 4, 30, "the fourth restart")
        assert p.history == [3, 3, 3, 4]
        assert p.next_backoff_s == pytest.approx(0.1)
    finally:
        launcher._stop.set()
        sup.join(timeout=10)
        if p.popen and p.popen.poll() is None:
            p.popen.kill()
            p.popen.wait(timeout=10)


def test_backoff_is_capped_at_max_backoff(tmp_path):
    policy = RestartPolicy(first_backoff_s=0.05, max_backoff_s=0.1, healthy_after_s=60.0)
    launcher = Launcher(tmp_path, restart_policy=policy)
    p = Proc("crashy", [sys.executable, "-S", "-c", "raise SystemExit(5)"], {}, tmp_path / "logs" / "crashy.log")
    launcher.procs.append(p)
    p.start()
    sup = threading.Thread(target=launcher._supervise, daemon=True)
    sup.start()
    try:
        # Uncapped, the second restart would leave 0.2 s for the next crash.
        _wait_for(lambda: p.restarts >= 2, 30, "two restarts")
        assert p.next_backoff_s == pytest.approx(0.1)
    finally:
        launcher._stop.set()
        sup.join(timeout=10)


@pytest.mark.parametrize("kwargs", [
    {"first_backoff_s": math.nan}, {"first_backoff_s": 0.0}, {"first_backoff_s": -1.0},
    {"max_backoff_s": math.inf}, {"first_backoff_s": 2.0, "max_backoff_s": 1.0},
    {"healthy_after_s": 0.0}, {"healthy_after_s": -5.0}, {"healthy_after_s": 1e9}, {"healthy_after_s": "10"},
    {"healthy_after_s": True},
])
def test_policy_refuses_values_out_of_range(kwargs):
    with pytest.raises(ValueError):
        RestartPolicy(**kwargs)


def test_default_policy_is_the_launchers():
    assert Launcher(".").restart_policy == RestartPolicy(first_backoff_s=0.5, max_backoff_s=30.0, healthy_after_s=10.0)
