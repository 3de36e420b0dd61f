"""The openai backend against a local HTTP server speaking the chat-completions protocol."""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from tests.unit.planner.planner_toyworld import ToyWorld, run_episode

from services.planner.core import POLICIES, OpenAIConfig, PolicyBackendError

pytestmark = pytest.mark.timeout(60)


class FakeChatServer:
    """Serves scripted answers; each script item is a str (the content) or ('sleep', seconds)."""

    def __init__(self, script):
        self.script = list(script)
        self.requests: list[dict] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_POST(self):  # noqa: N802 - http.server naming
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                outer.requests.append(body)
                item = outer.script.pop(0) if outer.script else '{"action": 0, "reasoning": "default"}'
                if isinstance(item, tuple) and item[0] == "sleep":
                    time.sleep(item[1])
                    item = '{"action": 0, "reasoning": "late"}'
                if isinstance(item, tuple) and item[0] == "status":
                    self.send_response(item[1])
                    self.send_header("Content-Type", "application/json")
                    self.end_headers()
                    self.wfile.write(b'{"error": {"message": "boom"}}')
                    return
                resp = {
                    "id": "chatcmpl-1", "object": "chat.completion", "created": 0, "model": body["model"],
                    "choices": [{"index": 0, "finish_reason": "stop",
                                 "message": {"role": "assistant", "content": item}}],
                    "usage": {"prompt_tokens": 1000, "completion_tokens": 50, "total_tokens": 1050},
                }
                data = json.dumps(resp).encode()
                try:
                    self.send_response(200)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(timeout=5)


def _world():
    return ToyWorld(landmarks={"sofa": (5.0, 0.0)}, rooms={})


def _cfg(url, **kw):
    base = dict(model="gpt-5.1", base_url=url, api_key="test", timeout_s=2.0, retries=0, backoff_initial_s=0.01)
    base.update(kw)
    return OpenAIConfig(**base)


def test_valid_answer_tokens_cost_and_request_shape(tmp_path):
    script = ['{"action": 0, "reasoning": "forward"}', '{"action": 0, "reasoning": "again"}']
    with FakeChatServer(script) as srv, POLICIES.create(
        "openai", _cfg(srv.url, reasoning_effort="low", save_prompts_dir=str(tmp_path))
    ) as policy:
        _, _, decisions = run_episode(_world(), policy, "walk to the sofa", max_steps=2)
        assert [d.reasoning for d in decisions] == ["forward", "again"]
        assert not any(d.fallback for d in decisions)
        assert policy.usage.calls == 2 and policy.usage.prompt_tokens == 2000 and policy.usage.completion_tokens == 100
        assert policy.usage.cost_usd == pytest.approx(2 * (1000 * 1.25 + 50 * 10.0) / 1e6)
        assert decisions[0].prompt_tokens == 1000 and decisions[0].backend == "openai:gpt-5.1"
    req = srv.requests[0]
    assert req["model"] == "gpt-5.1" and req["reasoning_effort"] == "low" and "temperature" not in req
    user = req["messages"][1]["content"]
    images = [p for p in user if p["type"] == "image_url"]
    assert images and all(p["image_url"]["url"].startswith("data:image/jpeg;base64,") for p in images)
    saved = tmp_path / "toy" / "step_000"
    assert (saved / "prompt.md").exists() and json.loads((saved / "answer.json").read_text())["answers"]


def test_garbage_gets_one_reask_then_heuristic_fallback():
    script = ["I think left is best", "still no json", '{"action": 0, "reasoning": "ok"}']
    with FakeChatServer(script) as srv, POLICIES.create("openai", _cfg(srv.url)) as policy:
        _, _, decisions = run_episode(_world(), policy, "walk to the sofa", max_steps=2)
    first, second = decisions
    assert first.fallback and "fallback (heuristic)" in first.reasoning
    assert first.prompt_tokens == 2000  # the answer and the re-ask were both paid for
    assert not second.fallback and second.reasoning == "ok"
    # The re-ask quoted the bad answer and said what was wrong.
    reask = srv.requests[1]["messages"]
    assert reask[-2] == {"role": "assistant", "content": "I think left is best"}
    assert "invalid" in reask[-1]["content"] and "JSON" in reask[-1]["content"]
    assert len(srv.requests) == 3


def test_reask_recovers_an_out_of_range_action():
    with FakeChatServer(['{"action": 99}', '{"action": 1, "reasoning": "fixed"}']) as srv, POLICIES.create(
        "openai", _cfg(srv.url)
    ) as policy:
        _, _, decisions = run_episode(_world(), policy, "walk to the sofa", max_steps=1)
        assert decisions[0].candidate_index == 1 and not decisions[0].fallback
        assert policy.usage.reasks == 1


def test_timeout_retries_then_stop_fallback():
    script = [("sleep", 1.5), ("sleep", 1.5)]
    with FakeChatServer(script) as srv, POLICIES.create(
        "openai", _cfg(srv.url, timeout_s=0.3, retries=1, fallback="stop")
    ) as policy:
        t0 = time.monotonic()
        traj, stopped, decisions = run_episode(_world(), policy, "walk to the sofa", max_steps=3)
        elapsed = time.monotonic() - t0
    assert stopped and decisions[0].fallback and decisions[0].kind.value == "stop"
    assert "APITimeoutError" in decisions[0].reasoning
    assert len(srv.requests) == 2  # one try + one retry
    assert elapsed < 5.0


def test_server_error_is_retried_and_client_error_raises_when_asked():
    with FakeChatServer([("status", 500), '{"action": 0, "reasoning": "after retry"}']) as srv, POLICIES.create(
        "openai", _cfg(srv.url, retries=2)
    ) as policy:
        _, _, decisions = run_episode(_world(), policy, "walk", max_steps=1)
        assert decisions[0].reasoning == "after retry" and len(srv.requests) == 2
    with FakeChatServer([("status", 400)]) as srv, POLICIES.create(
        "openai", _cfg(srv.url, retries=3, on_error="raise")
    ) as policy, pytest.raises(PolicyBackendError):
        run_episode(_world(), policy, "walk", max_steps=1)
    assert len(srv.requests) == 1  # a 400 is not retried


def test_missing_key_for_the_public_endpoint(monkeypatch):
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    with pytest.raises(PolicyBackendError):
        POLICIES.create("openai", {"model": "gpt-5.1"})
