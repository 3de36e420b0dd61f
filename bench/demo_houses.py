"""bench/demo_houses: the real ``make demo`` on other generated houses (issue 32 item 5).

    python -m bench.demo_houses                                   # the 10 default houses, one demo at a time
    python -m bench.demo_houses --houses generated:8 generated:3:floors=2 --fresh
    python -m bench.demo_houses --jobs 2                          # two demos at once (each is a whole system)

Each house runs ``python -m deploy.demo --scene <house> --run-dir runs/demo-houses/<slug>`` as a
subprocess: the router, the six services and the gateway, exploration, reconstruction and one mission
with the demo's default episode seed, exactly what a user's ``make demo --scene`` does. Nothing is run
in-process, so what this counts is what the demo prints: its ``RESULT:`` line (ne_m, success, steps,
spl), parsed here.

Output: ``runs/demo-houses/results.jsonl`` (one row per run, appended), ``table.md`` (the latest row of
each house asked for) and each demo's stdout in ``<slug>.log``. A house whose result is already in
``results.jsonl`` is skipped (resume) unless ``--fresh``. The last line printed is
``demo houses: K/N arrived`` over the N houses asked for.

A demo takes about 1.5-3 min on 2 shared cores; run one at a time there (``--jobs 1``, the default).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.common import table_markdown

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "runs" / "demo-houses"
# The houses of issue 32's check: five of one floor and five of two, none of them the default demo's
# generated:0.
HOUSES = ["generated:1:floors=2", "generated:2", "generated:3:floors=2", "generated:4", "generated:5:floors=2",
          "generated:6", "generated:7:floors=2", "generated:8", "generated:9:floors=2", "generated:10"]
# A whole demo explores for up to 900 s and navigates for up to 900 s (deploy.demo's own deadlines), plus
# start and stop: past this it is hung, not slow.
DEMO_TIMEOUT_S = 2100.0
HEADER = ("house", "ne_m", "success", "steps", "spl", "wall_s", "cpu_s", "note")

_RESULT = re.compile(r"RESULT: (?P<outcome>.*?) after (?P<steps>\d+) steps;(?P<metrics>.*)$")
_METRIC = re.compile(r"(\w+)=([^,\s]+)")


def slug(house: str) -> str:
    """A house's folder name: ``generated:3:floors=2`` -> ``generated-3-floors2`` (no ':' or '=' in paths)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "", house.replace(":", "-"))


def _value(text: str):
    if text in ("True", "False"):
        return text == "True"
    if text == "None":
        return None
    try:
        return float(text)
    except ValueError:
        return text


def parse_result(stdout: str) -> dict | None:
    """The last ``RESULT:`` line of a demo's stdout as {outcome, steps, ne_m, success, spl, ...}; None when
    the demo printed none (it failed before the mission ended)."""
    found = None
    for line in stdout.splitlines():
        m = _RESULT.search(line)
        if m:
            found = m
    if found is None:
        return None
    row = {"outcome": found["outcome"].strip(), "steps": int(found["steps"])}
    row.update({k: _value(v) for k, v in _METRIC.findall(found["metrics"])})
    return row


def load_results(path: Path) -> dict[str, dict]:
    """The latest row of each house in ``results.jsonl`` (a later run of a house replaces an earlier one)."""
    latest: dict[str, dict] = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                latest[row["house"]] = row
    return latest


def arrived(row: dict | None) -> bool:
    return bool(row) and row.get("success") is True


def summary_rows(houses: list[str], results: dict[str, dict]) -> list[tuple]:
    rows = []
    for h in houses:
        r = results.get(h)
        if r is None:
            rows.append((h, "-", "not run", "-", "-", "-", "-", ""))
            continue
        rows.append((h, r.get("ne_m", "-"), r.get("success", "-"), r.get("steps", "-"), r.get("spl", "-"),
                     r.get("wall_s", "-"), r.get("cpu_s", "-"), r.get("note", "")))
    return rows


def summary_line(houses: list[str], results: dict[str, dict]) -> str:
    return f"demo houses: {sum(arrived(results.get(h)) for h in houses)}/{len(houses)} arrived"


def run_demo(house: str, out: Path, timeout_s: float, extra: list[str]) -> dict:
    """One whole demo as a subprocess; its row (the parsed RESULT, exit code, wall and CPU seconds)."""
    run_dir = out / slug(house)
    log_path = out / f"{slug(house)}.log"
    cmd = [sys.executable, "-m", "deploy.demo", "--scene", house, "--run-dir", str(run_dir), *extra]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.monotonic()
    note = ""
    with log_path.open("w") as log:
        # Its own session, so a timeout stops the demo and every process it started (the demo stops its
        # children on SIGTERM; SIGKILL to the group if it does not).
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            rc, cpu_s = _wait(proc, timeout_s)
        except subprocess.TimeoutExpired:
            note = f"timed out after {timeout_s:.0f} s"
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                rc, cpu_s = _wait(proc, 30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                rc, cpu_s = _wait(proc, None)
    row = {"house": house, "rc": rc, "wall_s": round(time.monotonic() - t0, 1), "cpu_s": round(cpu_s, 1),
           "log": str(log_path.relative_to(ROOT)) if log_path.is_relative_to(ROOT) else str(log_path)}
    result = parse_result(log_path.read_text(errors="replace"))
    if result is None:
        note = note or f"no RESULT line (exit {rc})"
        row.update(success=False)
    else:
        row.update(result)
    row["note"] = note
    return row


def _wait(proc: subprocess.Popen, timeout_s: float | None) -> tuple[int, float]:
    """Exit code and the user+sys CPU seconds of the demo and every child it waited for (os.wait4's
    rusage), since wall time on shared cores says little."""
    end = None if timeout_s is None else time.monotonic() + timeout_s
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return proc.returncode, usage.ru_utime + usage.ru_stime
        if end is not None and time.monotonic() > end:
            raise subprocess.TimeoutExpired(proc.args, timeout_s)
        time.sleep(0.5)


def write_table(houses: list[str], results: dict[str, dict], out: Path) -> str:
    md = table_markdown("demo on other generated houses (deploy.demo, default episode seed)",
                        summary_rows(houses, results), HEADER)
    (out / "table.md").write_text(md + "\n" + summary_line(houses, results) + "\n")
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--houses", nargs="+", default=HOUSES, help="generated:N[:floors=2] scenes")
    ap.add_argument("--jobs", type=int, default=1, help="demos at once (each is a whole system)")
    ap.add_argument("--fresh", action="store_true", help="run every house again, even one already in results.jsonl")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--timeout-s", type=float, default=DEMO_TIMEOUT_S, help="per demo")
    ap.add_argument("--demo-args", default="", help="extra deploy.demo flags, e.g. '--seed 4'")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error("--jobs must be >= 1")
    args.out.mkdir(parents=True, exist_ok=True)
    results_path = args.out / "results.jsonl"
    results = load_results(results_path)
    todo = [h for h in dict.fromkeys(args.houses) if args.fresh or h not in results]
    for h in args.houses:
        if h not in todo:
            print(f"{h}: already in {results_path.name} (--fresh to run it again)", flush=True)

    lock = threading.Lock()

    def one(house: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {house}: demo started (log {args.out / (slug(house) + '.log')})",
              flush=True)
        row = run_demo(house, args.out, args.timeout_s, args.demo_args.split())
        print(f"[{time.strftime('%H:%M:%S')}] {house}: ne_m={row.get('ne_m')} success={row.get('success')} "
              f"steps={row.get('steps')} ({row['wall_s']:.0f} s wall, {row['cpu_s']:.0f} s CPU) {row['note']}",
              flush=True)
        with lock, results_path.open("a") as f:  # each row as it lands, so a stopped run resumes
            f.write(json.dumps(row) + "\n")
            results[house] = row

    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(one, todo))
    print("\n" + write_table(list(dict.fromkeys(args.houses)), results, args.out))
    print(summary_line(list(dict.fromkeys(args.houses)), results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
