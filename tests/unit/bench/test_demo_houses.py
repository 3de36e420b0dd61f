"""bench.demo_houses' bookkeeping: the demo's RESULT line parsed back, the resume and the summary line
(the demos themselves are the benchmark's job, not a unit test's)."""

from __future__ import annotations

import json

import pytest

from bench.demo_houses import load_results, main, parse_result, slug, summary_line
from deploy.demo import result_line


def _stdout(*lines: str) -> str:
    return "\n".join(f"[demo 13:00:00] {line}" for line in lines) + "\n"


def test_parses_the_line_the_demo_prints():
    metrics = {"ne_m": 2.4567, "success": True, "oracle_success": True, "spl": 0.8123, "ndtw": 0.5, "tl_m": 12.0}
    row = parse_result(_stdout("  step  3: at ( 1.00,  2.00)  5 candidates -> stop #None",
                               result_line("succeeded", 22, metrics), "stopped every process: {}"))
    assert row["steps"] == 22 and row["success"] is True and row["oracle_success"] is True
    assert row["ne_m"] == pytest.approx(2.46) and row["spl"] == pytest.approx(0.81)
    assert row["outcome"].startswith("ARRIVED")


def test_a_stop_short_of_the_goal_is_not_success():
    row = parse_result(_stdout(result_line("succeeded", 30, {"ne_m": 5.68, "success": False, "spl": 0.0})))
    assert row["success"] is False and row["ne_m"] == pytest.approx(5.68) and row["steps"] == 30
    assert "did not arrive" in row["outcome"]


def test_no_result_line_is_none():
    assert parse_result(_stdout("FAILED: TimeoutError: exploration did not finish")) is None


def test_slug_has_no_colons_or_equals():
    assert slug("generated:3:floors=2") == "generated-3-floors2"


def test_resume_skips_houses_already_run_and_counts_arrivals(tmp_path, capsys):
    rows = [{"house": "generated:2", "success": False, "ne_m": 9.0, "steps": 30},
            {"house": "generated:2", "success": True, "ne_m": 0.8, "steps": 12},  # a rerun replaces the first
            {"house": "generated:8", "success": False, "ne_m": 5.7, "steps": 30}]
    (tmp_path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert load_results(tmp_path / "results.jsonl")["generated:2"]["success"] is True
    # Both houses are already there, so nothing runs (a demo here would take minutes and fail the test's
    # isolation): only the table and the summary.
    assert main(["--out", str(tmp_path), "--houses", "generated:2", "generated:8"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1] == "demo houses: 1/2 arrived"
    table = (tmp_path / "table.md").read_text()
    assert "| generated:2 | 0.8 | True | 12 |" in table and "| generated:8 | 5.7 | False | 30 |" in table


def test_summary_counts_a_house_not_run_as_not_arrived():
    assert summary_line(["generated:1", "generated:2"], {"generated:1": {"success": True}}) == "demo houses: 1/2 arrived"
