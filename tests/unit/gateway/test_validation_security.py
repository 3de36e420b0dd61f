"""Bad input gets a clear 4xx with a reason; mutating routes need the token when one is set."""

from __future__ import annotations

import pytest

from shared.bus import FakeBus
from shared.bus.typed import TypedBus


@pytest.mark.parametrize("body, code, reason", [
    ({"instruction": "", "map_id": "house"}, 422, "instruction"),
    ({"instruction": "   ", "map_id": "house"}, 422, "instruction"),
    ({"instruction": "x" * 4001, "map_id": "house"}, 422, "instruction"),
    ({"instruction": "go", "map_id": "nowhere"}, 422, "unknown map"),
    ({"instruction": "go", "map_id": "../etc"}, 422, "map_id"),
    ({"instruction": "go", "map_id": "house", "options": {"max_steps": 0}}, 422, "max_steps"),
    ({"instruction": "go", "map_id": "house", "options": {"teleport": True}}, 422, "teleport"),
    ({"instruction": "go", "map_id": "house", "options": {"goal_m": [1, "a", 0]}}, 422, "goal_m"),
    ({"instruction": "go"}, 422, "map_id"),
    ({"instruction": "go", "map_id": "house", "extra": 1}, 422, "extra"),
    ({"instruction": "please refuse", "map_id": "house"}, 409, "scripted refusal"),
])
def test_bad_missions_get_a_clear_4xx(world, gateway, body, code, reason):
    with gateway() as client:
        r = client.post("/missions", json=body)
        assert r.status_code == code, r.text
        assert reason in r.text
        assert client.get("/missions").json()["total"] == 0  # nothing half-created


def test_planner_bad_request_maps_to_422(world, gateway):
    world.reconstructor.add_random("broken-map", 100)
    with gateway() as client:
        r = client.post("/missions", json={"instruction": "go", "map_id": "broken-map"})
    assert r.status_code == 422 and "cannot be navigated" in r.json()["detail"]


@pytest.mark.parametrize("raw", [b"{not json", b"", b"[1, 2]", b'"text"'])
def test_malformed_json_is_422_never_500(world, gateway, raw):
    with gateway() as client:
        r = client.post("/missions", content=raw, headers={"Content-Type": "application/json"})
    assert r.status_code == 422


def test_oversized_body_is_413(world, gateway):
    with gateway(max_body_bytes=2048) as client:
        r = client.post("/missions", json={"instruction": "x" * 3000, "map_id": "house"})
        assert r.status_code == 413 and "larger than 2048" in r.json()["detail"]

        def chunks():  # no Content-Length: the limit still holds
            yield b'{"instruction": "'
            yield b"x" * 4000
            yield b'", "map_id": "house"}'

        r = client.post("/missions", content=chunks(), headers={"Content-Type": "application/json"})
        assert r.status_code == 413


def test_missing_services_are_503_with_a_reason(net, gateway):
    with gateway() as client:  # nobody serves maps or missions
        r = client.post("/missions", json={"instruction": "go", "map_id": "house"})
        assert r.status_code == 503 and "unavailable" in r.json()["detail"]
        assert client.get("/maps").status_code == 503
        assert client.post("/explorations", json={}).status_code == 503
    with gateway(validate_map=False) as client:
        r = client.post("/missions", json={"instruction": "go", "map_id": "house"})
        assert r.status_code == 503 and "planner" in r.json()["detail"]
        assert client.get("/missions").json()["total"] == 0


def test_internal_service_failure_is_502_not_500(net, gateway):
    from shared import keys
    from shared.schemas import MapListReply, Ping

    bus = TypedBus(FakeBus(net), "broken")

    def boom(_: Ping) -> MapListReply:
        raise RuntimeError("disk on fire")

    bus.serve(keys.MAP_LIST.format(), Ping, boom)
    with gateway() as client:
        r = client.get("/maps")
    bus.raw.close()
    assert r.status_code == 502 and "disk on fire" in r.json()["detail"]


def test_token_protects_mutating_routes_only(world, gateway):
    with gateway(api_token="s3cret") as client:
        body = {"instruction": "go", "map_id": "house"}
        r = client.post("/missions", json=body)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert client.post("/missions", json=body, headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.post("/explorations", json={}).status_code == 401
        assert client.post("/maps?map_id=x", content=b"ply\n").status_code == 401
        assert client.post("/missions/m-x/cancel").status_code == 401
        assert client.post("/explorations/x-x/cancel").status_code == 401
        ok = client.post("/missions", json=body, headers={"Authorization": "Bearer s3cret"})
        assert ok.status_code == 202
        # Reading needs no token.
        assert client.get("/missions").status_code == 200
        assert client.get(f"/missions/{ok.json()['id']}").status_code == 200
        assert client.get("/dashboard").status_code == 200


def test_cors_is_configurable(world, gateway):
    with gateway(cors_origins=["http://ui.example"]) as client:
        r = client.options("/missions", headers={"Origin": "http://ui.example", "Access-Control-Request-Method": "POST"})
        assert r.headers["access-control-allow-origin"] == "http://ui.example"
    with gateway() as client:
        r = client.get("/missions", headers={"Origin": "http://ui.example"})
        assert "access-control-allow-origin" not in r.headers


def test_openapi_documents_every_route_with_a_response_model(world, gateway):
    with gateway() as client:
        spec = client.get("/openapi.json").json()
        assert client.get("/docs").status_code == 200
    paths = spec["paths"]
    for path in ["/missions", "/missions/{mission_id}", "/missions/{mission_id}/cancel", "/missions/{mission_id}/events",
                 "/explorations", "/explorations/{exploration_id}", "/explorations/{exploration_id}/cancel",
                 "/maps", "/maps/{map_id}",
                 "/maps/{map_id}/cloud.ply", "/status", "/health"]:
        assert path in paths, path
    assert "$ref" in str(paths["/missions/{mission_id}"]["get"]["responses"]["200"])
    assert "text/event-stream" in paths["/missions/{mission_id}/events"]["get"]["responses"]["200"]["content"]


def test_a_read_token_closes_every_get_but_health(world, gateway):
    with gateway(api_token="write-secret", read_token="read-secret") as client:
        r = client.post("/missions", json={"instruction": "go to the kitchen", "map_id": "house"},
                        headers={"Authorization": "Bearer write-secret"})
        assert r.status_code == 202, r.text
        mission = r.json()["id"]
        reads = ["/missions", f"/missions/{mission}", f"/missions/{mission}/history", "/maps", "/maps/house",
                 "/explorations", "/status", "/metrics"]
        for path in reads:
            assert client.get(path).status_code == 401, path
            assert client.get(path, headers={"Authorization": "Bearer wrong"}).status_code == 401, path
            assert client.get(path, headers={"Authorization": "Bearer read-secret"}).status_code == 200, path
            assert client.get(path, headers={"Authorization": "Bearer write-secret"}).status_code == 200, path
        assert client.get(f"/missions/{mission}", params={"access_token": "read-secret"}).status_code == 200
        assert client.get("/health").status_code == 200
        # The read token does not write.
        assert client.post("/missions", json={"instruction": "go", "map_id": "house"},
                           headers={"Authorization": "Bearer read-secret"}).status_code == 401


def test_nul_and_control_characters_in_upload_filenames_are_refused(world, gateway):
    with gateway() as client:
        for name in ("a\x00.ply", "a\nb.ply", "\x1f.pcd"):
            r = client.post("/maps", params={"map_id": "m", "filename": name}, content=b"ply\n",
                            headers={"Content-Type": "application/octet-stream"})
            assert r.status_code == 422, (name, r.text)


def test_huge_or_non_finite_numbers_in_free_form_options_are_422_not_500(world, gateway):
    """Found by schemathesis: the bus message refused them, the HTTP model did not (a 500)."""
    with gateway() as client:
        for options in ({"a": 1e300}, {"a": [1, {"b": -1e16}]}):
            r = client.post("/explorations", json={"options": options})
            assert r.status_code == 422, r.text
        r = client.post("/missions", json={"instruction": "go to the kitchen", "map_id": "house",
                                           "options": {"policy_config": {"t": 1e300}}})
        assert r.status_code == 422, r.text
