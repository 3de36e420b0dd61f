"""Reliability report (``python -m bench.reliability``, ``make reliability``): runs the reliability
suite - long variants included unless ``--quick`` - and prints what was injected and what survived."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROWS = [
    ("faults_injected", "process faults injected (SIGKILL)"), ("faults_survived", "  ... restarted and survived"),
    ("missions_under_fault", "missions running under a fault"), ("missions_failed_cleanly", "  ... failed with a reason"),
    ("missions_resumed", "  ... succeeded anyway"), ("map_writes_killed", "map imports killed mid-write"),
    ("bus_payloads_fuzzed", "bus payloads fuzzed (queries)"), ("bus_payloads_answered_typed", "  ... answered bad_request"),
    ("bus_samples_fuzzed", "bad samples published to subscribers"), ("http_cases_generated", "HTTP cases (schemathesis)"),
    ("http_5xx", "  ... 5xx answers"), ("auth_refusals_checked", "unauthenticated mutations refused"),
    ("missions_checked", "missions checked across a gateway kill"), ("events_checked", "  ... their events"),
    ("missions_lost", "missions lost"), ("events_lost", "events lost"),
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the default (bounded) tests only")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        marker = "not slow" if args.quick else "slow or not slow"
        t0 = time.time()
        rc = subprocess.call([sys.executable, "-m", "pytest", "-q", "-m", marker, "tests/reliability"],
                             env={**__import__("os").environ, "ANT_RELIABILITY_REPORT": str(report)})
        counts = json.loads(report.read_text())["counts"] if report.exists() else {}
    print(f"\nreliability report ({'quick' if args.quick else 'full'}, {time.time() - t0:.0f} s, tests rc={rc})")
    for key, label in ROWS:
        print(f"  {label:<42} {counts.get(key, 0):>7}")
    lost = counts.get("missions_lost", 0) + counts.get("events_lost", 0) + counts.get("http_5xx", 0)
    print(f"  {'verdict':<42} {'OK' if rc == 0 and lost == 0 else 'FAILED':>7}")
    return 0 if rc == 0 and lost == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
