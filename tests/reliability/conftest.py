"""Fixtures of the reliability suite: an in-process live system and a tally (the launched system,
``system``, is shared with tests/e2e: tests/conftest.py).

The tally is what ``python -m bench.reliability`` prints: every test adds what it injected and what
survived (faults, fuzzed payloads, HTTP cases, 5xx answers, lost missions and events). Where
``ANT_RELIABILITY_REPORT`` names a file, the session's tally is written there as JSON.
"""

from __future__ import annotations

import json
import os
import threading
from collections import Counter
from pathlib import Path

import pytest

# The launched system (``system``) is tests/conftest.py's, shared with tests/e2e; these names stay importable
# from here, where the reliability tests always found them.
from tests.launched import MAP_ID, SCENE, scene_ply, wait_until  # noqa: F401  (re-exported)


class Tally:
    """Counters shared by every reliability test of a session (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.notes: list[str] = []

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counts[name] += n

    def note(self, text: str) -> None:
        with self._lock:
            self.notes.append(text)


@pytest.fixture(scope="session")
def tally():
    t = Tally()
    yield t
    path = os.environ.get("ANT_RELIABILITY_REPORT")
    if path:
        Path(path).write_text(json.dumps({"counts": dict(t.counts), "notes": t.notes}, indent=1))


@pytest.fixture(scope="session")
def live(tmp_path_factory):
    """Every service that serves a queryable, in this process, each on its own zenoh session behind a
    real zenoh router (see tests/reliability/live.py), with one map imported."""
    from tests.reliability.live import live_system

    with live_system(tmp_path_factory.mktemp("live"), map_ply=scene_ply(density_per_m2=20.0)) as system:
        yield system


@pytest.fixture
def live_gateway(live, tmp_path):
    """``live_gateway(**settings)``: a TestClient of a gateway on its own zenoh session of ``live``."""
    from contextlib import contextmanager

    from fastapi.testclient import TestClient

    from services.gateway.app import create_app
    from tests.reliability.live import gateway_settings

    @contextmanager
    def make(**overrides):
        from shared import keys
        from shared.bus.typed import RemoteError
        from shared.schemas import MapInfo, MapRequest
        from tests.reliability.live import LIVE_MAP

        with TestClient(create_app(gateway_settings(live, tmp_path, **overrides))) as client:
            # A zenoh session just opened may answer a query "nobody serves it" at once, before the
            # router has told it of the queryables: wait until the gateway's own session reaches the
            # map store, as the process system's fixture waits for GET /maps.
            def reaches_map() -> bool:
                try:
                    client.app.state.bus.request(keys.MAP_INFO.format(map=LIVE_MAP), MapRequest(map_id=LIVE_MAP),
                                                 MapInfo, timeout_s=2.0)
                    return True
                except RemoteError:
                    return False

            wait_until(reaches_map, 20, "the gateway's session reaches the map store")
            yield client

    return make
