"""When the reaper takes a job's worker for gone (services/gateway/reaper.py orphan_reason)."""

from services.gateway.reaper import orphan_reason

OWNER = {"service": "mapper", "instance": "mapper-0", "started_s": 100.0}


def test_a_worker_whose_token_the_query_missed_but_whose_info_answers_is_alive():
    # A loaded gateway's liveliness query can end without a busy worker's reply; its info still answers
    # with the incarnation that took the job, so the job is not failed.
    assert orphan_reason(OWNER, "mapper", alive=set(), started={"mapper-0": 100.0}) is None
    assert orphan_reason(OWNER, "mapper", alive=set(), started={"mapper-0": 100.0}, dropped=True) is None


def test_a_worker_neither_seen_nor_answering_went_away():
    assert orphan_reason(OWNER, "mapper", alive=set(), started={}) == "the mapper mapper-0 that ran it went away"
    # Another instance answering does not keep this one's job.
    assert "went away" in orphan_reason(OWNER, "mapper", alive={"mapper-1"}, started={"mapper-1": 5.0})


def test_a_worker_restarted_under_its_name_lost_the_job_with_or_without_its_token():
    for alive in (set(), {"mapper-0"}):
        reason = orphan_reason(OWNER, "mapper", alive=alive, started={"mapper-0": 200.0})
        assert reason is not None and "restarted" in reason


def test_a_live_worker_keeps_its_job():
    assert orphan_reason(OWNER, "mapper", alive={"mapper-0"}, started={"mapper-0": 100.0}) is None
    assert orphan_reason(OWNER, "mapper", alive={"mapper-0"}, started={}) is None
