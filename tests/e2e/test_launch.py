"""The real thing: ``make up`` (a zenoh router and six service processes), used as a person would use it."""

import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import httpx
import pytest

from deploy.launcher import SERVICES, free_port
from deploy.up import api_token

pytestmark = [pytest.mark.e2e, pytest.mark.system]
ROOT = Path(__file__).resolve().parents[2]
SMALL_SCENE = "generated:3:area=50"


def _read_until(proc: subprocess.Popen, pattern: str, timeout_s: float, seen: list[str]) -> re.Match:
    """Lines of ``proc``'s stdout until one matches ``pattern`` (a reader thread: readline can block)."""
    found: list[re.Match] = []
    done = threading.Event()

    def reader():
        for line in proc.stdout:
            seen.append(line)
            m = re.search(pattern, line)
            if m:
                found.append(m)
                break
        done.set()

    threading.Thread(target=reader, daemon=True).start()
    if not done.wait(timeout_s) or not found:
        proc.kill()
        raise AssertionError(f"no line matching {pattern!r} within {timeout_s} s; output:\n{''.join(seen)}")
    return found[0]


def test_make_up_serves_the_api_with_a_token_until_ctrl_c(tmp_path):
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "ANT_API_TOKEN"}
    # A small house: robot-io builds its scene before it is alive, and serving the API does not depend on it.
    proc = subprocess.Popen([sys.executable, "-m", "deploy.up", "--port", str(port), "--run-dir", str(tmp_path),
                             "--scene", SMALL_SCENE],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seen: list[str] = []
    try:
        url = _read_until(proc, r"dashboard\s+(http://\S+)/dashboard", 240, seen).group(1)
        token = _read_until(proc, r"API token\s+(\S+)", 10, seen).group(1)
        _read_until(proc, r"running; Ctrl-C", 10, seen)
        assert url == f"http://127.0.0.1:{port}"
        # The token was generated at first start, kept private, and is what the gateway checks.
        token_file = tmp_path / "api_token"
        assert token_file.read_text().strip() == token and len(token) >= 24
        assert token_file.stat().st_mode & 0o777 == 0o600
        with httpx.Client(base_url=url, timeout=10) as http:
            assert http.get("/health").json()["status"] == "ok"
            assert http.get("/dashboard").status_code == 200
            status = http.get("/status").json()
            assert status["all_alive"] is True
            seen_services = {s["service"]: s for s in status["services"]}
            assert sorted(seen_services) == sorted(SERVICES)
            assert all(s["instances"] == 1 and s["details"][0]["version"] for s in seen_services.values())
            assert http.post("/missions", json={}).status_code == 401
            # With the token the request passes authentication and fails validation instead.
            assert http.post("/missions", json={}, headers={"Authorization": f"Bearer {token}"}).status_code == 422
        proc.send_signal(signal.SIGINT)
        codes = _read_until(proc, r"stopped every process: (\{.*\})", 60, seen).group(1)
        assert proc.wait(30) == 0
        assert re.findall(r": (-?\d+|None)", codes) and set(re.findall(r": (-?\d+|None)", codes)) == {"0"}, codes
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def test_the_token_is_kept_per_run_dir_and_the_environment_overrides_it(tmp_path, monkeypatch):
    monkeypatch.delenv("ANT_API_TOKEN", raising=False)
    first = api_token(tmp_path)
    assert api_token(tmp_path) == first
    assert api_token(tmp_path / "other") != first
    monkeypatch.setenv("ANT_API_TOKEN", "from-env")
    assert api_token(tmp_path) == "from-env"
