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
    # issue 15: poisoned state, forged events, stuck missions, budgets
    ("bus_numbers_fuzzed", "bad numbers on every queryable (nan/inf/huge)"),
    ("bus_numbers_refused", "  ... refused bad_request"), ("probes_after_fuzz", "  ... each followed by a probe"),
    ("poisoned_states", "poisoned states"),
    ("forged_announcements", "forged map announcements"), ("forged_announcements_ignored", "  ... ignored"),
    ("forged_events_sent", "forged events (every kind x state)"), ("replayed_events_sent", "replayed events"),
    ("forged_or_replayed_accepted", "forged or replayed events accepted"),
    ("kill_pairs", "kill pairs (gateway + planner, planner restart)"), ("stuck_missions", "stuck missions"),
    ("orphans_cancelled", "orphans cancelled"), ("budget_abuse_attempts", "budget abuse attempts"),
    ("budget_refused_typed", "  ... refused budget_exceeded"), ("http_bad_inputs_checked", "bad HTTP inputs (422)"),
    # issue 15 item 12: memory (ANT_UPLOAD_MEMORY_MB sets the upload's size)
    ("upload_memory_bytes", "upload streamed through (bytes)"),
    ("upload_peak_growth_mb_gateway", "  ... gateway peak RSS growth (MB)"),
    ("upload_peak_growth_mb_reconstructor", "  ... reconstructor peak RSS growth (MB)"),
]
# Must be 0 for the verdict to be OK.
MUST_BE_ZERO = ("missions_lost", "events_lost", "http_5xx", "poisoned_states", "forged_or_replayed_accepted",
                "stuck_missions")


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
    lost = sum(counts.get(k, 0) for k in MUST_BE_ZERO)
    print(f"  {'verdict':<42} {'OK' if rc == 0 and lost == 0 else 'FAILED':>7}")
    return 0 if rc == 0 and lost == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
