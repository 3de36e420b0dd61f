"""Security: with ``ANT_API_TOKEN`` set, every mutating route of the OpenAPI schema refuses a request
without the token (401), or with a wrong one, and accepts it with the token; reading needs none.

The bus side - a service cannot publish, serve or declare liveliness on another service's key
expressions - is proven against a real zenoh router with the generated ACL in
``tests/contract/test_acl.py`` (deploy/zenoh); this module checks that that test exists and covers
publishing, so the claim cannot silently go away.
"""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from tests.reliability.http_server import live_gateway

MUTATING = {"post", "put", "patch", "delete"}
TOKEN = "rel-s3cret-token"


def _concrete(path: str) -> str:
    return path.replace("{mission_id}", "m-none").replace("{exploration_id}", "x-none").replace("{map_id}", "house")


def _request(http: httpx.Client, method: str, path: str, headers: dict[str, str]) -> httpx.Response:
    if path.startswith("/maps") and method == "post":
        return http.request(method, path, params={"map_id": "sec-map", "filename": "c.ply"},
                            content=b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n",
                            headers={**headers, "Content-Type": "application/octet-stream"})
    body = {"instruction": "go to the kitchen", "map_id": "house"} if path == "/missions" else {}
    return http.request(method, path, json=body, headers=headers)


def test_every_mutating_route_needs_the_token(tmp_path, tally):
    with live_gateway(tmp_path, api_token=TOKEN) as (url, _world), httpx.Client(base_url=url, timeout=10) as http:
        spec = http.get("/openapi.json").json()
        routes = [(m, _concrete(p)) for p, ops in spec["paths"].items() for m in ops if m in MUTATING]
        assert {("post", "/missions"), ("post", "/explorations"), ("post", "/maps")} <= set(routes), routes
        for method, path in routes:
            for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"},
                            {"Authorization": f"Bearer {TOKEN}x"}):
                r = _request(http, method, path, headers)
                assert r.status_code == 401, (method, path, headers, r.status_code, r.text)
                assert r.headers.get("www-authenticate") == "Bearer"
                tally.add("auth_refusals_checked")
            ok = _request(http, method, path, {"Authorization": f"Bearer {TOKEN}"})
            # Accepted past authentication: whatever the route then says, it is not 401, and never 5xx.
            assert ok.status_code != 401 and ok.status_code < 500, (method, path, ok.status_code, ok.text)
        # Nothing was created by the refused requests; the accepted mission exists.
        missions = http.get("/missions").json()
        assert missions["total"] == 1
        for path, ops in spec["paths"].items():
            if "get" in ops and "{" not in path and path not in ("/missions/{mission_id}/events",):
                r = http.get(path, timeout=5) if not path.endswith("events") else None
                assert r is None or r.status_code != 401, path


def test_the_acl_contract_test_covers_cross_service_publishing():
    acl_test = Path(__file__).resolve().parents[1] / "contract" / "test_acl.py"
    if not acl_test.is_file():
        pytest.fail("tests/contract/test_acl.py (the zenoh ACL test from deploy/) is missing")
    text = acl_test.read_text()
    for name in ("test_a_service_publishes_on_its_own_keys_only", "test_a_service_serves_its_own_queryables_only",
                 "test_liveliness_of_another_service_cannot_be_forged"):
        assert f"def {name}" in text, name
