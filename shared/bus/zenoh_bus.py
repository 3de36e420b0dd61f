"""The real bus: one zenoh session behind the :class:`~shared.bus.base.Bus` port."""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict

import zenoh
import zenoh.ext as zx

from shared.bus.base import (
    Bus, Closeable, Dispatcher, LivelinessHandler, Overloaded, Payload, QueryHandler, QueryTarget,
    Reply, SampleHandler, as_keys, run_query_handler,
)
from shared.allocator import tune_for_large_messages
from shared.bus.config import ZenohSettings, zenoh_config

log = logging.getLogger(__name__)

_TARGETS = {QueryTarget.BEST: zenoh.QueryTarget.BEST_MATCHING, QueryTarget.ALL: zenoh.QueryTarget.ALL}


class _Declared:
    def __init__(self, *undeclare, dispatcher: Dispatcher | None = None):
        self._undeclare = undeclare
        self.dispatcher = dispatcher
        self._lock = threading.Lock()
        self._closed = False

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for fn in self._undeclare:
            try:
                fn()
            except Exception:  # the session may already be closed
                log.debug("undeclare failed", exc_info=True)


class ZenohBus(Bus):
    def __init__(self, settings: ZenohSettings | None = None, *, session: zenoh.Session | None = None):
        tune_for_large_messages()
        self.settings = settings or ZenohSettings()
        self.session = session or zenoh.open(zenoh_config(self.settings))
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._durables: OrderedDict[str, zx.AdvancedPublisher] = OrderedDict()
        self.max_durable_keys = 64  # job event streams kept queryable; older ones are released
        self._pub_lock = threading.Lock()
        self._owned: list[Closeable] = []

    def _track(self, d):
        self._owned.append(d)
        return d

    def publish(self, key: str, payload: Payload, *, cache: int = 0) -> None:
        if cache > 0:
            self._durable(key, cache).put(bytes(payload) if isinstance(payload, memoryview) else payload)
            return
        # A declared publisher per key skips per-put key resolution on the hot path.
        pub = self._publishers.get(key)
        if pub is None:
            with self._pub_lock:
                pub = self._publishers.get(key)
                if pub is None:
                    # BLOCK, not DROP: a map chunk or a mission event must not vanish under load.
                    pub = self._publishers[key] = self.session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.BLOCK
                    )
        pub.put(bytes(payload) if isinstance(payload, memoryview) else payload)

    def _durable(self, key: str, cache: int):
        """zenoh-ext's advanced publisher: a sample cache that late/restarted subscribers query."""
        with self._pub_lock:
            pub = self._durables.pop(key, None)
            if pub is None:
                pub = zx.declare_advanced_publisher(
                    self.session, key, congestion_control=zenoh.CongestionControl.BLOCK,
                    cache=zx.CacheConfig(max_samples=cache),
                    sample_miss_detection=zx.MissDetectionConfig(heartbeat=1.0), publisher_detection=True)
            self._durables[key] = pub  # most recently used last
            while len(self._durables) > self.max_durable_keys:
                _, old = self._durables.popitem(last=False)
                old.undeclare()
            return pub

    def release(self, key: str) -> None:
        with self._pub_lock:
            pub = self._durables.pop(key, None)
        if pub is not None:
            pub.undeclare()

    def subscribe(self, key: str, handler: SampleHandler, *, max_queue: int = 256,
                  history: bool = False) -> Closeable:
        disp = Dispatcher(f"sub:{key}", 1, max_queue)

        def on_sample(sample: zenoh.Sample) -> None:
            k, data = str(sample.key_expr), sample.payload.to_bytes()
            try:
                disp.submit(lambda: handler(k, data))
            except Overloaded:
                log.warning("subscriber %s is behind: dropped a sample", key)

        if history:
            sub = zx.declare_advanced_subscriber(
                self.session, key, on_sample, history=zx.HistoryConfig(detect_late_publishers=True),
                recovery=zx.RecoveryConfig(heartbeat=True), subscriber_detection=True)
        else:
            sub = self.session.declare_subscriber(key, on_sample)
        return self._track(_Declared(sub.undeclare, disp.close))

    def query(self, key, payload=None, *, timeout_s=5.0, target=QueryTarget.BEST) -> list[Reply]:
        kwargs = {"target": _TARGETS[QueryTarget(target)], "timeout": timeout_s}
        if payload is not None:
            kwargs["payload"] = bytes(payload) if isinstance(payload, memoryview) else payload
        if target == QueryTarget.ALL:
            kwargs["consolidation"] = zenoh.ConsolidationMode.NONE
        replies = []
        for r in self.session.get(key, **kwargs):
            if r.ok is not None:
                replies.append(Reply(str(r.ok.key_expr), r.ok.payload.to_bytes(), None))
            else:
                replies.append(Reply(key, None, r.err.payload.to_bytes()))
        return replies

    def serve(self, key, handler: QueryHandler, *, workers: int = 1, max_queue: int = 64) -> Closeable:
        all_keys = as_keys(key)
        disp = Dispatcher(f"q:{all_keys[0]}", workers, max_queue)
        return self._track(_Declared(*[self._declare_queryable(k, handler, disp) for k in all_keys], disp.close,
                                     dispatcher=disp))

    def _declare_queryable(self, key: str, handler: QueryHandler, disp: Dispatcher):
        reply_key = None if "*" in key else key
        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else None

            def job():
                try:
                    ok, out = run_query_handler(handler, str(query.key_expr), payload)
                    if ok:
                        # A queryable on a wildcard (ant/maps/*/info) answers on the concrete key asked.
                        query.reply(reply_key if reply_key else str(query.key_expr), out)
                    else:
                        query.reply_err(out)
                finally:
                    query.drop()  # finalises the query: the asker stops waiting for us

            try:
                disp.submit(job)
            except Overloaded as exc:
                query.reply_err(str(exc).encode())
                query.drop()

        return self.session.declare_queryable(key, on_query, complete=True).undeclare

    def liveliness_token(self, key: str) -> Closeable:
        tok = self.session.liveliness().declare_token(key)
        return self._track(_Declared(tok.undeclare))

    def watch_liveliness(self, key: str, handler: LivelinessHandler) -> Closeable:
        disp = Dispatcher(f"live:{key}", 1, 1024)

        def on_sample(sample: zenoh.Sample) -> None:
            k, alive = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
            try:
                disp.submit(lambda: handler(k, alive))
            except Overloaded:
                log.warning("liveliness watcher %s is behind", key)

        sub = self.session.liveliness().declare_subscriber(key, on_sample, history=True)
        return self._track(_Declared(sub.undeclare, disp.close))

    def alive(self, key: str, *, timeout_s: float = 2.0) -> list[str]:
        return sorted(
            {str(r.ok.key_expr) for r in self.session.liveliness().get(key, timeout=timeout_s) if r.ok is not None}
        )

    def close(self) -> None:
        for d in reversed(self._owned):
            d.close()
        self._owned.clear()
        for pub in [*self._publishers.values(), *self._durables.values()]:
            try:
                pub.undeclare()
            except Exception:
                pass
        self._publishers.clear()
        self._durables.clear()
        try:
            self.session.close()
        except Exception:
            log.debug("session close failed", exc_info=True)
