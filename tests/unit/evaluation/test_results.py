"""Results log (append, resume, crash tails) and the summary tables."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest

from evaluation.errors import ResultsFormatError
from shared.vln_metrics import MetricsError, episode_metrics, euclidean_geodesic
from evaluation.results import (
    COLUMNS, EpisodeResult, ResultsLog, csv_table, markdown_table, metrics_from_dict, summary_row, write_tables,
)


def done(eid: str, final_xy, goal_xy=(0.0, 0.0), stop=True, ref=True, latency=(0.1, 0.3), tokens=(50, 5)):
    traj = np.array([[10.0, 0.0, 0.0], [*final_xy, 0.0]])
    goal = np.array([*goal_xy, 0.0])
    m = episode_metrics(traj, goal, geodesic=euclidean_geodesic, stop_called=stop,
                        reference_path_m=np.array([[10.0, 0, 0], [5.0, 0, 0], [0.0, 0, 0]]) if ref else None)
    return EpisodeResult(episode_id=eid, scene_id="s", status="done", metrics=m.to_dict(), trajectory_m=traj.tolist(),
                         step_latency_s=list(latency), prompt_tokens=tokens[0], completion_tokens=tokens[1],
                         cost_usd=0.25)


def test_log_last_line_per_episode_wins(tmp_path):
    log = ResultsLog(tmp_path / "r.jsonl")
    assert log.load() == {}
    log.append(EpisodeResult(episode_id="1", scene_id="s", status="error", reason="timeout"))
    log.append(done("2", (1.0, 0.0)))
    log.append(done("1", (0.5, 0.0)))
    got = log.load()
    assert list(got) == ["1", "2"]
    assert got["1"].status == "done" and got["1"].metrics["success"] is True


def test_log_drops_and_cuts_a_partial_tail(tmp_path):
    path = tmp_path / "r.jsonl"
    log = ResultsLog(path)
    log.append(done("1", (0.5, 0.0)))
    whole = path.read_bytes()
    path.write_bytes(whole + b'{"episode_id": "2", "scene_')  # killed mid-write
    assert list(log.load()) == ["1"]
    log.append(done("3", (0.5, 0.0)))
    assert list(log.load()) == ["1", "3"]
    assert path.read_bytes().startswith(whole) and path.read_bytes().count(b"\n") == 2


def test_log_refuses_a_corrupt_line_in_the_middle(tmp_path):
    path = tmp_path / "r.jsonl"
    log = ResultsLog(path)
    log.append(done("1", (0.5, 0.0)))
    path.write_bytes(path.read_bytes() + b"not json\n")
    log.append(done("2", (0.5, 0.0)))
    with pytest.raises(ResultsFormatError, match=":2:"):
        log.load()


def test_metrics_from_dict_accepts_dropped_nulls_but_not_missing_fields():
    m = done("1", (50.0, 0.0), ref=False).metrics
    stripped = {k: v for k, v in m.items() if v is not None}  # what the gateway's record keeps
    back = metrics_from_dict(stripped)
    assert back.ndtw is None and back.sdtw is None and back.ne_m == pytest.approx(50.0)
    with pytest.raises(MetricsError, match="spl"):
        metrics_from_dict({k: v for k, v in m.items() if k != "spl"})


def test_summary_row_matches_an_independent_average():
    results = [done("1", (0.5, 0.0)), done("2", (4.0, 0.0)), done("3", (1.0, 0.0), stop=False),
               EpisodeResult(episode_id="4", scene_id="s", status="skipped", reason="scene not found"),
               EpisodeResult(episode_id="5", scene_id="s", status="error", reason="timeout")]
    row = summary_row(results, "heuristic")
    ms = [r.metrics for r in results[:3]]
    assert row["label"] == "heuristic" and row["count"] == 3 and row["skipped"] == 1 and row["errors"] == 1
    assert row["SR"] == pytest.approx(round(100 * np.mean([m["success"] for m in ms]), 1))
    assert row["SR"] == pytest.approx(33.3)  # only episode 1 stopped within 3 m
    assert row["OSR"] == pytest.approx(66.7)
    assert row["NE"] == pytest.approx(round(np.mean([0.5, 4.0, 1.0]), 2))
    assert row["TL"] == pytest.approx(round(np.mean([9.5, 6.0, 9.0]), 2))
    assert row["SPL"] == pytest.approx(round(100 * np.mean([m["spl"] for m in ms]), 1))
    assert row["nDTW"] == pytest.approx(round(100 * np.mean([m["ndtw"] for m in ms]), 1))
    assert row["step_s"] == pytest.approx(0.2) and row["tokens"] == pytest.approx(55.0)
    assert row["cost_usd"] == pytest.approx(0.75)


def test_summary_row_without_finished_episodes_has_no_metrics():
    row = summary_row([EpisodeResult(episode_id="1", scene_id="s", status="skipped")], "x")
    assert row["count"] == 0 and row["skipped"] == 1
    assert all(row[k] is None for k in ("NE", "SR", "SPL", "nDTW"))
    assert "| x | 0 | 1 | 0 | 0 | - |" in markdown_table([row])


def test_tables_round_trip(tmp_path):
    rows = [summary_row([done("1", (0.5, 0.0))], "a"), summary_row([done("2", (9.0, 0.0))], "b")]
    md, cs = write_tables(rows, tmp_path / "t", title="T")
    lines = md.read_text().splitlines()
    assert lines[0] == "# T" and lines[2].startswith("| label | count |")
    assert len([ln for ln in lines if ln.startswith("| a |") or ln.startswith("| b |")]) == 2
    parsed = list(csv.DictReader(io.StringIO(cs.read_text())))
    assert [r["label"] for r in parsed] == ["a", "b"] and list(parsed[0]) == COLUMNS
    for row, back in zip(rows, parsed):
        for k in ("SR", "SPL", "NE", "nDTW"):
            assert float(back[k]) == pytest.approx(row[k])
    assert csv_table([{"label": "z"}]).splitlines()[1].startswith("z,,")
    assert math.isclose(float(parsed[1]["NE"]), 9.0)
