"""In-memory bus with the same interface and threading model as the zenoh one (dora's MockNode).

Payloads are copied to ``bytes`` on the way through, as a network would, so a test cannot pass by
sharing a mutable buffer between sender and receiver.
"""

from __future__ import annotations

import threading
from collections import deque
from concurrent.futures import Future, wait

from shared.bus.base import (
    Bus, Closeable, Dispatcher, LivelinessHandler, Overloaded, Payload, QueryHandler, QueryTarget,
    Reply, SampleHandler, as_keys, run_query_handler,
)
from shared.bus.keyexpr import intersects


class _Entity:
    def __init__(self, on_close, dispatcher: Dispatcher | None = None):
        self._on_close = on_close
        self.dispatcher = dispatcher
        self._closed = False

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._on_close()


class FakeBus(Bus):
    """Many FakeBus handles can share one :class:`FakeNetwork` to model several processes."""

    def __init__(self, network: FakeNetwork | None = None):
        self.net = network or FakeNetwork()
        self._owned: list[Closeable] = []

    # Every entity this handle declares is closed with it, like a zenoh session.
    def _track(self, entity):
        self._owned.append(entity)
        return entity

    def publish(self, key: str, payload: Payload, *, cache: int = 0) -> None:
        data = bytes(payload)
        if cache > 0:
            with self.net.lock:
                q = self.net.cache.get(key)
                if q is None or q.maxlen != cache:
                    q = self.net.cache[key] = deque(q or (), maxlen=cache)
                q.append(data)
        for sub_key, disp, handler in list(self.net.subs):
            if intersects(sub_key, key):
                try:
                    disp.submit(lambda h=handler: h(key, data))
                except Overloaded:
                    pass  # a slow subscriber drops samples, as zenoh's bounded channels do

    def release(self, key: str) -> None:
        with self.net.lock:
            self.net.cache.pop(key, None)

    def subscribe(self, key: str, handler: SampleHandler, *, max_queue: int = 256,
                  history: bool = False) -> Closeable:
        disp = Dispatcher(f"sub:{key}", 1, max_queue)
        entry = (key, disp, handler)
        with self.net.lock:
            if history:
                for k, q in self.net.cache.items():
                    if intersects(key, k):
                        for data in q:
                            disp.submit(lambda h=handler, k=k, d=data: h(k, d))
            self.net.subs.append(entry)

        def close():
            with self.net.lock:
                self.net.subs.remove(entry)
            disp.close()

        return self._track(_Entity(close))

    def query(self, key, payload=None, *, timeout_s=5.0, target=QueryTarget.BEST) -> list[Reply]:
        data = None if payload is None else bytes(payload)
        with self.net.lock:
            matches = [q for q in self.net.queryables if intersects(q[0], key)]
        if target == QueryTarget.BEST:
            # Round-robin across replicas, standing in for zenoh's choice of one queryable.
            self.net.rr += 1
            matches = matches[self.net.rr % len(matches):][:1] if matches else []
        futures: list[Future] = []
        for q_key, disp, handler in matches:
            fut: Future = Future()
            futures.append(fut)

            def job(h=handler, f=fut, k=q_key):
                ok, out = run_query_handler(h, key, data)
                f.set_result(Reply(k if "*" not in k else key, bytes(out) if ok else None,
                                   None if ok else bytes(out)))

            try:
                disp.submit(job)
            except Overloaded as exc:
                fut.set_result(Reply(q_key, None, str(exc).encode()))
        done, _ = wait(futures, timeout=timeout_s)
        return [f.result() for f in futures if f in done]

    def serve(self, key, handler: QueryHandler, *, workers: int = 1, max_queue: int = 64) -> Closeable:
        all_keys = as_keys(key)
        disp = Dispatcher(f"q:{all_keys[0]}", workers, max_queue)
        entries = [(k, disp, handler) for k in all_keys]
        with self.net.lock:
            self.net.queryables.extend(entries)

        def close():
            with self.net.lock:
                for e in entries:
                    self.net.queryables.remove(e)
            disp.close()

        return self._track(_Entity(close, disp))

    def liveliness_token(self, key: str) -> Closeable:
        with self.net.lock:
            self.net.tokens[key] = self.net.tokens.get(key, 0) + 1
            watchers = list(self.net.watchers)
        for w_key, h in watchers:
            if intersects(w_key, key):
                h(key, True)

        def close():
            with self.net.lock:
                self.net.tokens[key] -= 1
                gone = self.net.tokens[key] == 0
                if gone:
                    del self.net.tokens[key]
                watchers = list(self.net.watchers)
            if gone:
                for w_key, h in watchers:
                    if intersects(w_key, key):
                        h(key, False)

        return self._track(_Entity(close))

    def watch_liveliness(self, key: str, handler: LivelinessHandler) -> Closeable:
        entry = (key, handler)
        with self.net.lock:
            self.net.watchers.append(entry)
            current = [k for k in self.net.tokens if intersects(key, k)]
        for k in current:
            handler(k, True)

        def close():
            with self.net.lock:
                self.net.watchers.remove(entry)

        return self._track(_Entity(close))

    def alive(self, key: str, *, timeout_s: float = 2.0) -> list[str]:
        with self.net.lock:
            return sorted(k for k in self.net.tokens if intersects(key, k))

    def close(self) -> None:
        for e in reversed(self._owned):
            e.close()
        self._owned.clear()


class FakeNetwork:
    """The shared state that several FakeBus handles talk through."""

    def __init__(self):
        self.lock = threading.RLock()
        self.subs: list = []
        self.queryables: list = []
        self.tokens: dict[str, int] = {}
        self.watchers: list = []
        self.cache: dict[str, deque] = {}
        self.rr = 0
