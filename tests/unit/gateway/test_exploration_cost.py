"""What naming a map's rooms cost (the reconstructor's MLLM labeller, issue 32) reaches the ledger as a
mission's decisions do: the stored map's info -> the mapper's ExplorationFinished -> the gateway's
exploration record (tokens and dollars)."""

from __future__ import annotations

from services.gateway.records import apply_event, empty_summary
from services.mapper.core.exploration_job import labelling_usage
from shared.schemas import (
    ExplorationFinished, ExplorationStarted, JobEvent, JobEventKind, JobState, MapInfo, MapLabelling,
)


def _info(labelling: MapLabelling | None) -> MapInfo:
    return MapInfo(map_id="house", version=2, point_count=10, bounds_min_m=(0, 0, 0), bounds_max_m=(1, 1, 1),
                   labelling=labelling)


def test_the_labelling_cost_of_a_map_is_the_exploration_cost():
    lab = MapLabelling(labeller="mllm", model="gpt-4o-mini", regions=3, rooms_named=3, calls=3, prompt_tokens=900,
                       completion_tokens=60, cost_usd=0.0042, cache_hits=1)
    usage = labelling_usage(_info(lab))
    assert (usage.calls, usage.prompt_tokens, usage.completion_tokens, usage.cost_usd, usage.cache_hits) == \
        (3, 900, 60, 0.0042, 1)
    assert labelling_usage(_info(None)).calls == 0  # a map stored without a labeller costs nothing
    summary = empty_summary()
    events = [JobEvent(job_id="x1", seq=0, kind=JobEventKind.STARTED, state=JobState.RUNNING,
                       data=ExplorationStarted(map_id="house")),
              JobEvent(job_id="x1", seq=1, kind=JobEventKind.FINISHED, state=JobState.SUCCEEDED,
                       data=ExplorationFinished(map_id="house", version=2, points=10, regions=3, usage=usage))]
    for ev in events:
        apply_event(summary, ev, {})
    assert (summary["prompt_tokens"], summary["completion_tokens"], summary["cost_usd"]) == (900, 60, 0.0042)
