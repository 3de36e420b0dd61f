"""A small synchronous client of the gateway's HTTP API (what the runner needs, nothing more).

It wraps an ``httpx.Client`` so tests can hand in FastAPI's ``TestClient`` (an ``httpx.Client`` too)
and drive a real gateway app in-process.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import httpx

from shared.schemas import SceneSummary

from evaluation.errors import GatewayError, MissionTimeout

log = logging.getLogger(__name__)

TERMINAL_STATES = frozenset({"succeeded", "failed", "cancelled"})


class GatewayClient:
    """``GatewayClient(http)`` over an ``httpx.Client`` whose ``base_url`` is the gateway.

    Every method raises :class:`GatewayError` (with the HTTP status) when the gateway refuses or
    cannot be reached; 503 answers (a service momentarily unreachable) are retried ``retries`` times.
    """

    def __init__(self, http: httpx.Client, *, token: str | None = None, retries: int = 3, retry_wait_s: float = 1.0):
        self.http = http
        self.headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.retries, self.retry_wait_s = retries, retry_wait_s

    @classmethod
    def connect(cls, base_url: str, *, token: str | None = None, timeout_s: float = 120.0) -> GatewayClient:
        return cls(httpx.Client(base_url=base_url, timeout=timeout_s), token=token)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> GatewayClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- plumbing ------------------------------------------------------------------------------------
    def _call(self, method: str, url: str, raw: bool = False, **kw) -> Any:
        headers = {**self.headers, **kw.pop("headers", {})}
        for attempt in range(self.retries + 1):
            try:
                r = self.http.request(method, url, headers=headers, **kw)
            except httpx.HTTPError as exc:
                if attempt < self.retries:
                    time.sleep(self.retry_wait_s)
                    continue
                raise GatewayError(f"{method} {url}: gateway unreachable ({exc})", 0) from None
            if r.status_code == 503 and attempt < self.retries:
                log.info("%s %s: 503, retrying in %.1f s", method, url, self.retry_wait_s)
                time.sleep(self.retry_wait_s)
                continue
            if r.status_code >= 400:
                try:
                    detail = r.json().get("detail", r.text)
                except ValueError:
                    detail = r.text
                raise GatewayError(f"{method} {url}: {r.status_code} {detail}", r.status_code)
            if raw:
                return r.content
            return r.json() if r.content else None
        raise AssertionError("unreachable")

    # --- API -------------------------------------------------------------------------------------------
    def health(self) -> dict[str, Any]:
        return self._call("GET", "/health")

    def load_scene(self, scene: str) -> SceneSummary:
        """Switch robot-io's scene through the gateway (``POST /robot/scene``)."""
        return SceneSummary.model_validate(self._call("POST", "/robot/scene", json={"scene": scene}))

    def submit_mission(self, instruction: str, map_id: str, options: dict[str, Any]) -> str:
        """POST /missions; returns the mission id."""
        return self._call("POST", "/missions", json={"instruction": instruction, "map_id": map_id,
                                                     "options": options})["id"]

    def mission(self, mission_id: str) -> dict[str, Any]:
        return self._call("GET", f"/missions/{mission_id}")

    def history(self, mission_id: str, after: int = -1, limit: int = 1000) -> list[dict[str, Any]]:
        return self._call("GET", f"/missions/{mission_id}/history", params={"after": after, "limit": limit})

    def recording(self, mission_id: str) -> bytes:
        """The mission's Rerun recording (``.rrd`` bytes); 404 unless it was recorded."""
        return self._call("GET", f"/missions/{mission_id}/recording.rrd", raw=True)

    def cancel_mission(self, mission_id: str) -> None:
        self._cancel(f"/missions/{mission_id}/cancel")

    def submit_exploration(self, map_id: str, **body: Any) -> str:
        return self._call("POST", "/explorations", json={"map_id": map_id, **body})["id"]

    def exploration(self, exploration_id: str) -> dict[str, Any]:
        return self._call("GET", f"/explorations/{exploration_id}")

    def cancel_exploration(self, exploration_id: str) -> None:
        self._cancel(f"/explorations/{exploration_id}/cancel")

    def _cancel(self, path: str) -> None:
        try:
            self._call("POST", path)
        except GatewayError as exc:
            if exc.status != 409:  # already ended: nothing to cancel
                raise

    def maps(self) -> list[dict[str, Any]]:
        return self._call("GET", "/maps")

    def map_info(self, map_id: str) -> dict[str, Any] | None:
        """The map's metadata, or None when the gateway says it does not exist."""
        try:
            return self._call("GET", f"/maps/{map_id}")
        except GatewayError as exc:
            if exc.status == 404:
                return None
            raise

    def upload_map(self, map_id: str, data: bytes, filename: str = "cloud.ply") -> dict[str, Any]:
        return self._call("POST", "/maps", params={"map_id": map_id, "filename": filename}, content=data,
                          headers={"Content-Type": "application/octet-stream"})

    def wait(self, getter, job_id: str, timeout_s: float, poll_s: float = 0.2,
             until: Callable[[dict[str, Any]], bool] | None = None) -> dict[str, Any]:
        """Poll ``getter(job_id)`` until its state is terminal, or until ``until(record)`` is true of a
        running one (the caller then holds a record that is not terminal); :class:`MissionTimeout` past
        the deadline."""
        end = time.monotonic() + timeout_s
        delay = min(poll_s, 0.05)
        while True:
            rec = getter(job_id)
            if rec["state"] in TERMINAL_STATES or (until is not None and until(rec)):
                return rec
            if time.monotonic() > end:
                raise MissionTimeout(f"{job_id} still {rec['state']} after {timeout_s:.0f} s (step {rec.get('step')})")
            time.sleep(delay)
            # Short first polls for short jobs, then the configured pace.
            delay = min(poll_s, delay * 2)
