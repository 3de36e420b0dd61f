"""An exploration's events and a map written to .rrd, read back with rerun's own reader."""

from __future__ import annotations

import numpy as np
import rerun as rr

from shared.recording import RecordedEvent, RecordingInput, entity_rows, write_recording
from shared.schemas import (
    ExplorationFinished, ExplorationProgress, ExplorationStarted, JobEvent, JobEventKind, JobState,
)


def test_exploration_recording_has_progress_events_and_the_built_map(tmp_path):
    progress = [0.02, 0.3, 0.55, 0.8, 0.85]
    events = [JobEvent(job_id="x-1", seq=0, kind=JobEventKind.STARTED, state=JobState.RUNNING,
                           data=ExplorationStarted(map_id="m"))]
    events += [JobEvent(job_id="x-1", seq=i + 1, kind=JobEventKind.PROGRESS, state=JobState.RUNNING,
                            data=ExplorationProgress(stage="touring", progress=p, message=f"stage {i}"))
               for i, p in enumerate(progress)]
    events.append(JobEvent(job_id="x-1", seq=len(events), kind=JobEventKind.FINISHED,
                               state=JobState.SUCCEEDED,
                               data=ExplorationFinished(map_id="m", version=1, points=20_000, regions=2)))
    events = [RecordedEvent.from_message(e) for e in events]
    xyz = np.random.default_rng(0).uniform(0, 5, (20_000, 3)).astype(np.float32)
    path = write_recording(RecordingInput("x-1", "exploration", events[::-1], xyz, np.zeros_like(xyz, np.uint8), "m"),
                           tmp_path / "x-1.rrd", max_points=5000)
    assert not (tmp_path / "x-1.rrd.part").exists()
    rows = entity_rows(path)
    assert rows["events"] == len(events) and rows["progress"] == len(progress)
    assert rows["world/map"] == 1 and "decisions" not in rows
    for chunk in rr.chunk.RrdReader(str(path)).stream():
        if chunk.entity_path.lstrip("/") == "world/map":
            assert chunk.is_static and len(chunk.to_record_batch().column("Points3D:positions")[0]) == 5000
        if chunk.entity_path.lstrip("/") == "progress":
            # the step timeline of an exploration is the event seq, written in order whatever the input order
            steps = chunk.to_record_batch().column("step").to_pylist()
            assert steps == sorted(steps) == list(range(1, len(progress) + 1))
