"""The ``Bus`` port: what services need from a message bus, and nothing zenoh-specific.

Two implementations: :class:`shared.bus.zenoh_bus.ZenohBus` (the real one) and
:class:`shared.bus.fake.FakeBus` (in memory, for unit tests). Both hand incoming samples and queries
to the same :class:`Dispatcher`: a bounded queue drained by worker threads, so that no handler ever
runs inside a transport callback (a slow handler would stall zenoh's own threads) and a flood of
requests is refused with an "overloaded" error instead of growing memory without bound.

Payloads are bytes-like; typing and validation live one layer up (:mod:`shared.bus.typed`).
"""

from __future__ import annotations

import logging
import queue
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol

log = logging.getLogger(__name__)

Payload = bytes | bytearray | memoryview


class Closeable(Protocol):
    def close(self) -> None: ...


# What ``Bus.serve`` returns also carries its ``dispatcher`` (for the queue depth in metrics).


@dataclass(frozen=True)
class Reply:
    """One answer to a query: ``payload`` when ok, ``error`` when the replier reported an error."""

    key: str
    payload: bytes | None = None
    error: bytes | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


class QueryTarget(StrEnum):
    BEST = "best"  # one matching queryable answers (load is shared between replicas)
    ALL = "all"  # every matching queryable answers (e.g. info from every instance)


class QueryFailed(Exception):
    """Raised by a query handler to send ``payload`` back as an error reply."""

    def __init__(self, payload: Payload):
        super().__init__("query failed")
        self.payload = bytes(payload)


QueryHandler = Callable[[str, bytes | None], Payload]
SampleHandler = Callable[[str, bytes], None]
LivelinessHandler = Callable[[str, bool], None]


class Bus(ABC):
    """Publish/subscribe, queries, queryables and liveliness over key expressions."""

    @abstractmethod
    def publish(self, key: str, payload: Payload, *, cache: int = 0) -> None:
        """Publish a sample. ``cache > 0`` keeps the last ``cache`` samples of this key at the
        publisher, so that a subscriber asking for ``history`` gets them even if it (re)started
        after they were sent - the way mission events survive a gateway restart."""

    @abstractmethod
    def release(self, key: str) -> None:
        """Drop the publisher cache of ``key`` (the job it belonged to is long over)."""

    @abstractmethod
    def subscribe(self, key: str, handler: SampleHandler, *, max_queue: int = 256,
                  history: bool = False) -> Closeable:
        """Deliver every sample on ``key`` (may contain wildcards), in order, on a worker thread;
        with ``history``, first the samples that publishers still cache, and samples detected as
        missed are recovered from them (duplicates are possible: receivers dedupe)."""

    @abstractmethod
    def query(
        self, key: str, payload: Payload | None = None, *, timeout_s: float = 5.0,
        target: QueryTarget = QueryTarget.BEST,
    ) -> list[Reply]: ...

    @abstractmethod
    def serve(
        self, key: str | Sequence[str], handler: QueryHandler, *, workers: int = 1, max_queue: int = 64
    ) -> Closeable:
        """Answer queries on ``key`` (or on each of several keys, sharing one worker pool) with
        ``handler``; it returns the reply payload or raises :class:`QueryFailed` (any other
        exception becomes an error reply with its message)."""

    @abstractmethod
    def liveliness_token(self, key: str) -> Closeable: ...

    @abstractmethod
    def watch_liveliness(self, key: str, handler: LivelinessHandler) -> Closeable:
        """Call ``handler(token_key, alive)`` for tokens matching ``key``: the ones alive now, then changes."""

    @abstractmethod
    def alive(self, key: str, *, timeout_s: float = 2.0) -> list[str]:
        """Keys of the liveliness tokens matching ``key`` that are alive now."""

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Overloaded(Exception):
    pass


class Dispatcher:
    """A bounded work queue drained by ``workers`` daemon threads.

    ``submit`` never blocks (it is called from transport callbacks); when the queue is full it raises
    :class:`Overloaded` so the caller can answer with an error at once.
    """

    def __init__(self, name: str, workers: int = 1, max_queue: int = 64):
        self.name = name
        self._q: queue.Queue = queue.Queue(maxsize=max_queue)
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._run, name=f"{name}-{i}", daemon=True) for i in range(max(1, workers))
        ]
        for t in self._threads:
            t.start()

    @property
    def depth(self) -> int:
        return self._q.qsize()

    def submit(self, fn: Callable[[], None]) -> None:
        if self._stop.is_set():
            raise Overloaded(f"{self.name} is closed")
        try:
            self._q.put_nowait(fn)
        except queue.Full:
            raise Overloaded(f"{self.name}: {self._q.maxsize} requests already queued") from None

    def _run(self) -> None:
        while True:
            fn = self._q.get()
            if fn is None:
                return
            try:
                fn()
            except Exception:  # a handler bug must not kill the worker
                log.exception("unhandled error in %s", self.name)

    def close(self, timeout_s: float = 2.0) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        for _ in self._threads:
            try:
                self._q.put(None, timeout=timeout_s)
            except queue.Full:
                break
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout_s)


def as_keys(key: str | Sequence[str]) -> list[str]:
    return [key] if isinstance(key, str) else list(key)


def run_query_handler(handler: QueryHandler, key: str, payload: bytes | None) -> tuple[bool, Payload]:
    """Run a handler; returns (ok, payload). Shared by both buses so errors look the same."""
    try:
        return True, handler(key, payload)
    except QueryFailed as exc:
        return False, exc.payload
    except Exception as exc:  # the typed layer normally catches first; this is the last line
        log.exception("query handler for %s failed", key)
        return False, f"{type(exc).__name__}: {exc}".encode()
