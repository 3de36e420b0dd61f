"""deploy.healthcheck picks the right instance and fails closed."""

from __future__ import annotations

import pytest

from deploy import healthcheck as hc


def tokens(*pairs):
    return [f"ant/alive/{s}/{i}" for s, i in pairs]


def test_picks_the_named_instance_or_this_hosts_one(monkeypatch):
    monkeypatch.setattr(hc.socket, "gethostname", lambda: "c0ffee12.local")
    alive = tokens(("renderer", "c0ffee12-local-7"), ("renderer", "other-host-1"), ("planner", "c0ffee12-local-9"))
    assert hc.pick_instance(alive, "renderer", None, False) == "c0ffee12-local-7"
    assert hc.pick_instance(alive, "renderer", "other-host-1", False) == "other-host-1"
    assert hc.pick_instance(alive, "planner", None, True) == "c0ffee12-local-9"
    with pytest.raises(hc.Unhealthy, match="not alive"):
        hc.pick_instance(alive, "renderer", "renderer-9", False)
    with pytest.raises(hc.Unhealthy, match="no mapper instance"):
        hc.pick_instance(alive, "mapper", None, True)
    monkeypatch.setattr(hc.socket, "gethostname", lambda: "elsewhere")
    with pytest.raises(hc.Unhealthy, match="of host"):
        hc.pick_instance(alive, "renderer", None, False)


def test_gateway_check_fails_when_nothing_listens(monkeypatch):
    from deploy.launcher import free_port

    monkeypatch.setenv("ANT_PORT", str(free_port()))
    assert hc.main(["gateway", "--timeout-s", "0.5"]) == 1
    with pytest.raises(hc.Unhealthy):
        hc.check_http(f"http://127.0.0.1:{free_port()}/health", timeout_s=0.5)
