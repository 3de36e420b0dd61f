"""GET /status: an instance is alive when its liveliness token or its info answers (as the job reaper
judges a worker): a loaded system's liveliness query can end without a busy instance's reply."""

from __future__ import annotations

import pytest

from services.gateway.routes import status as status_route
from shared.schemas import ServiceInfo

SERVICES = status_route.EXPECTED


def _info(service: str) -> ServiceInfo:
    return ServiceInfo(service=service, version="1.2.3", instance=f"{service}-0", started_s=1.0)


@pytest.mark.parametrize("missing_token, missing_info, alive", [
    (None, None, True),
    ("robot_io", None, True),      # its token's reply was lost; its info answered: alive, with its version
    (None, "mapper", True),        # its info did not answer; its token is up: alive, version unknown
    ("planner", "planner", False),  # neither answered: not alive
])
def test_alive_is_a_token_or_an_answered_info(world, gateway, monkeypatch, missing_token, missing_info, alive):
    monkeypatch.setattr(status_route.ServicesClient, "alive",
                        lambda self, service=None: [(s, f"{s}-0") for s in SERVICES if s != missing_token])
    monkeypatch.setattr(status_route.ServicesClient, "infos",
                        lambda self, service=None: [_info(s) for s in SERVICES if s != missing_info])
    with gateway() as client:
        body = client.get("/status").json()
    assert body["all_alive"] is alive
    seen = {s["service"]: s["details"][0] for s in body["services"]}
    assert sorted(seen) == sorted(s for s in SERVICES if not (s == missing_token == missing_info))
    for service, detail in seen.items():
        assert detail["instance"] == f"{service}-0"
        assert detail["version"] == (None if service == missing_info else "1.2.3")
