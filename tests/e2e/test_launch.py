"""The real thing: a zenoh router and six service processes, checked through the gateway."""

import httpx
import pytest

from deploy.launcher import SERVICES, Launcher

pytestmark = pytest.mark.e2e


def test_six_services_come_up_answer_and_stop_cleanly(tmp_path):
    launcher = Launcher(tmp_path, restart=False)
    with launcher:
        with httpx.Client(base_url=launcher.gateway_url, timeout=10) as http:
            assert http.get("/health").json()["status"] == "ok"
            status = http.get("/status").json()
        assert status["all_alive"] is True
        seen = {s["service"]: s for s in status["services"]}
        assert sorted(seen) == sorted(SERVICES)
        for s in seen.values():
            assert s["instances"] == 1 and s["details"][0]["version"]
    codes = launcher.stop()
    assert all(code == 0 for code in codes.values()), codes
