"""Bad input over HTTP: schemathesis generates requests from the gateway's own OpenAPI schema
(valid and invalid bodies, parameters, headers) against a real uvicorn server; not one 5xx."""

from __future__ import annotations

import importlib.util

import httpx
import pytest

from tests.reliability.http_server import live_gateway

# Imported where the requests are generated, not here: schemathesis and hypothesis cost ~2 s to import,
# and under xdist every worker imports every test module to collect it, while one worker runs this file.
pytestmark = pytest.mark.skipif(importlib.util.find_spec("schemathesis") is None,
                                reason="could not import 'schemathesis'")

# SSE streams stay open while a job runs; schemathesis reads them whole, so give each call a bound.
TIMEOUT_S = 5.0


def run_schemathesis(url: str, tally, max_examples: int) -> tuple[int, list]:
    import schemathesis
    from hypothesis import HealthCheck, given, settings

    spec = httpx.get(f"{url}/openapi.json", timeout=5).json()
    schema = schemathesis.openapi.from_dict(spec)
    cases = 0
    failures: list = []
    for result in schema.get_all_operations():
        operation = result.ok()

        @settings(max_examples=max_examples, deadline=None, database=None, derandomize=True,
                  suppress_health_check=list(HealthCheck))
        def check(case):
            nonlocal cases
            response = case.call(base_url=url, timeout=TIMEOUT_S)
            cases += 1
            if response.status_code >= 500:
                failures.append((case.method, case.formatted_path, case.path_parameters, case.query,
                                 str(case.body)[:200], response.status_code, response.text[:300]))

        strategy = operation.as_strategy()
        given(strategy)(check)()
    tally.add("http_cases_generated", cases)
    tally.add("http_5xx", len(failures))
    return cases, failures


def test_schemathesis_finds_no_5xx(tmp_path, tally):
    with live_gateway(tmp_path) as (url, _world):
        cases, failures = run_schemathesis(url, tally, max_examples=15)
    assert cases >= 100
    assert not failures, failures[:5]


def test_schemathesis_with_a_token_finds_no_5xx(tmp_path, tally):
    with live_gateway(tmp_path, api_token="s3cret") as (url, _world):
        cases, failures = run_schemathesis(url, tally, max_examples=8)
    assert cases >= 50 and not failures, failures[:5]


@pytest.mark.slow
def test_schemathesis_long_run(tmp_path, tally):
    with live_gateway(tmp_path) as (url, _world):
        cases, failures = run_schemathesis(url, tally, max_examples=150)
    assert not failures, failures[:5]
