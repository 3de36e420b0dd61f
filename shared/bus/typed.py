"""Typed messaging over any :class:`~shared.bus.base.Bus`: encode, decode, typed errors.

* :meth:`TypedBus.serve` decodes the request (which checks every number's range and finiteness),
  checks its budget (:meth:`~shared.schemas.Message.check_budget`), calls the handler and encodes its result; *any*
  exception (bad payload, validation, a bug) becomes an :class:`~shared.schemas.ErrorReply`, so a bad
  request never kills a service and the asker always learns why.
* :meth:`TypedBus.request` raises :class:`RemoteError` with that code when the other side failed and
  :class:`NoReplyError` when nobody answered in time.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TypeVar

from shared import keys
from shared.bus.base import Bus, Closeable, QueryFailed, QueryTarget, Reply
from shared.codec import CodecError, decode, decode_any, encode
from shared.schemas import BudgetExceeded, ErrorCode, ErrorReply, Message
from shared.telemetry import Telemetry

log = logging.getLogger(__name__)

Req = TypeVar("Req", bound=Message)
Rep = TypeVar("Rep", bound=Message)


class RemoteError(RuntimeError):
    """The replier answered with an error."""

    def __init__(self, code: ErrorCode, message: str, service: str = "", key: str = ""):
        super().__init__(f"{service or 'remote'} [{code}] {message}" + (f" (on {key})" if key else ""))
        self.code, self.message, self.service, self.key = code, message, service, key


class NoReplyError(RemoteError):
    """Nobody answered: within the timeout (a service busy or hung), or - when the query ended early -
    because nobody serves the key any more (a service that is gone)."""

    def __init__(self, key: str, timeout_s: float, elapsed_s: float | None = None):
        if elapsed_s is not None and elapsed_s < 0.9 * timeout_s:
            what = f"nobody serves it (the query ended after {elapsed_s:.1f} s without a reply)"
        else:
            what = f"no reply within {timeout_s:.1f} s"
        super().__init__(ErrorCode.UNAVAILABLE, what, "", key)
        self.timeout_s, self.elapsed_s = timeout_s, elapsed_s


class NotFound(LookupError):
    """Raise from a handler to answer NOT_FOUND (unknown map, mission, ...)."""


def error_for(exc: BaseException) -> tuple[ErrorCode, str]:
    """Map an exception raised while serving to an error code and a message for the asker."""
    if isinstance(exc, CodecError):
        return ErrorCode.BAD_REQUEST, str(exc)
    if isinstance(exc, NotFound):
        return ErrorCode.NOT_FOUND, str(exc)
    if isinstance(exc, BudgetExceeded):
        return ErrorCode.BUDGET_EXCEEDED, str(exc)
    if isinstance(exc, (ValueError, TypeError)):
        return ErrorCode.BAD_REQUEST, f"{type(exc).__name__}: {exc}"
    if isinstance(exc, TimeoutError):
        return ErrorCode.TIMEOUT, str(exc) or "timed out"
    if isinstance(exc, RemoteError):
        return ErrorCode.UNAVAILABLE if exc.code == ErrorCode.UNAVAILABLE else exc.code, str(exc)
    return ErrorCode.INTERNAL, f"{type(exc).__name__}: {exc}"


class Replicas:
    """The live instances of one service, from liveliness, handed out round-robin.

    zenoh sends a query to *one* matching queryable (the nearest), so replicas of a service would
    not share the load by themselves; a client that wants them to addresses each instance's own
    route (:func:`shared.keys.routed`) in turn, and moves to the next one when an instance is gone
    or overloaded.
    """

    def __init__(self, bus: Bus, service: str):
        self._lock = threading.Lock()
        self._instances: list[str] = []
        self._next = 0
        prefix = keys.ALIVE.pattern(service=service)
        self._watch = bus.watch_liveliness(prefix, self._on_token)
        # The watch delivers current tokens asynchronously; seed the list so the first call balances.
        for token in bus.alive(prefix, timeout_s=1.0):
            self._on_token(token, True)

    def _on_token(self, token: str, alive: bool) -> None:
        instance = token.rsplit("/", 1)[-1]
        with self._lock:
            if alive and instance not in self._instances:
                self._instances.append(instance)
                self._instances.sort()
            elif not alive and instance in self._instances:
                self._instances.remove(instance)

    def order(self) -> list[str]:
        """All live instances, starting with the next one in turn."""
        with self._lock:
            n = len(self._instances)
            if not n:
                return []
            start = self._next % n
            self._next += 1
            return self._instances[start:] + self._instances[:start]

    def close(self) -> None:
        self._watch.close()


class TypedBus:
    def __init__(self, bus: Bus, service: str = "client", telemetry: Telemetry | None = None,
                 max_request_bytes: int = 256 * 1024 * 1024):
        self.raw = bus
        self.service = service
        self.telemetry = telemetry
        self.max_request_bytes = max_request_bytes
        self._replicas_lock = threading.Lock()
        self._replica_sets: dict[str, Replicas] = {}

    # --- publish / subscribe ---------------------------------------------------------------------
    def publish(self, key: str, msg: Message, *, cache: int = 0) -> None:
        self.raw.publish(key, encode(msg), cache=cache)

    def subscribe(self, key: str, model: type[Rep], handler: Callable[[str, Rep], None], *,
                  history: bool = False) -> Closeable:
        def on_sample(k: str, data: bytes) -> None:
            try:
                msg = decode(data, model, self.max_request_bytes)
            except CodecError as exc:
                # A bad sample is dropped and counted; the subscriber keeps going.
                log.warning("dropped bad sample on %s: %s", k, exc)
                if self.telemetry:
                    self.telemetry.record(f"sub:{key}", 0.0, ok=False)
                return
            t0 = time.perf_counter()
            ok = True
            try:
                handler(k, msg)
            except Exception:
                ok = False
                log.exception("subscriber handler for %s failed", k)
            if self.telemetry:
                self.telemetry.record(f"sub:{key}", time.perf_counter() - t0, ok)

        return self.raw.subscribe(key, on_sample, history=history)

    # --- queries ---------------------------------------------------------------------------------
    def serve(self, key: str, model: type[Req], handler: Callable[..., Message], *,
              workers: int = 1, max_queue: int = 64, name: str | None = None,
              instance: str | None = None, keyed: bool = False) -> Closeable:
        """Serve ``key``; with ``instance``, also its instance route (for balancing clients),
        both fed to the same worker pool. ``keyed``: the handler is ``handler(key, request)`` with the
        concrete key asked - what a queryable on a wildcard (``ant/*/planner/...``) learns the robot from."""
        endpoint = name or key

        def on_query(k: str, payload: bytes | None) -> bytes:
            t0 = time.perf_counter()
            try:
                if payload is None:
                    raise CodecError("empty", "the query carries no payload")
                request = decode(payload, model, self.max_request_bytes)
                request.check_budget()  # before any work: an over-budget request costs nothing
                result = handler(k, request) if keyed else handler(request)
                out = encode(result)
            except Exception as exc:
                code, message = error_for(exc)
                level = logging.ERROR if code == ErrorCode.INTERNAL else logging.INFO
                log.log(level, "%s on %s: %s", code, k, message, exc_info=code == ErrorCode.INTERNAL)
                if self.telemetry:
                    self.telemetry.record(endpoint, time.perf_counter() - t0, ok=False)
                raise QueryFailed(encode(ErrorReply(code=code, message=message, service=self.service)))
            if self.telemetry:
                self.telemetry.record(endpoint, time.perf_counter() - t0, ok=True)
            return out

        routes = [key] if instance is None else [key, keys.routed(key, instance)]
        entity = self.raw.serve(routes, on_query, workers=workers, max_queue=max_queue)
        disp = getattr(entity, "dispatcher", None)
        if self.telemetry is not None and disp is not None:
            self.telemetry.watch_depth(endpoint, lambda: disp.depth)
        return entity

    def _decode_reply(self, key: str, reply: Reply, model: type[Rep]) -> Rep:
        data = reply.payload if reply.ok else reply.error
        try:
            msg = decode_any(data, {model.SCHEMA: model, ErrorReply.SCHEMA: ErrorReply})
        except CodecError as exc:
            if not reply.ok:  # a transport-level error (e.g. overloaded) carries plain text
                raise RemoteError(ErrorCode.UNAVAILABLE, (data or b"").decode(errors="replace"), "", key) from None
            raise RemoteError(ErrorCode.INTERNAL, f"undecodable reply: {exc}", "", key) from exc
        if isinstance(msg, ErrorReply):
            raise RemoteError(msg.code, msg.message, msg.service, key)
        return msg

    def request(self, key: str, msg: Message, model: type[Rep], *, timeout_s: float = 10.0,
                balance: str | None = None) -> Rep:
        """Ask one queryable on ``key``. With ``balance=<service>``, spread requests over that
        service's live replicas in turn; an instance that is gone, silent or overloaded is skipped
        for the next one, so a dying replica costs a retry, not a failed request."""
        payload = self._encode_request(key, msg)
        if balance:
            for instance in self._replicas(balance).order():
                route = keys.routed(key, instance)
                replies = self.raw.query(route, payload, timeout_s=timeout_s, target=QueryTarget.BEST)
                if not replies:
                    continue
                try:
                    return self._decode_reply(route, replies[0], model)
                except RemoteError as exc:
                    if exc.code != ErrorCode.UNAVAILABLE:
                        raise
        t0 = time.monotonic()
        replies = self.raw.query(key, payload, timeout_s=timeout_s, target=QueryTarget.BEST)
        if not replies:
            raise NoReplyError(key, timeout_s, time.monotonic() - t0)
        return self._decode_reply(key, replies[0], model)

    @staticmethod
    def _encode_request(key: str, msg: Message) -> bytes:
        # A request that cannot be encoded (an integer beyond 64 bits in a free-form dict, say) is
        # the asker's bad request, reported like the replier would report it.
        try:
            return encode(msg)
        except CodecError as exc:
            raise RemoteError(ErrorCode.BAD_REQUEST, f"the request cannot be sent: {exc}", "local", key) from None

    def _replicas(self, service: str) -> Replicas:
        with self._replicas_lock:
            r = self._replica_sets.get(service)
            if r is None:
                r = self._replica_sets[service] = Replicas(self.raw, service)
            return r

    def close(self) -> None:
        with self._replicas_lock:
            for r in self._replica_sets.values():
                r.close()
            self._replica_sets.clear()

    def request_all(self, key: str, msg: Message, model: type[Rep], *,
                    timeout_s: float = 2.0) -> list[Rep | RemoteError]:
        """Ask every matching queryable; each answer is a result or the RemoteError it sent."""
        out: list[Rep | RemoteError] = []
        for r in self.raw.query(key, self._encode_request(key, msg), timeout_s=timeout_s, target=QueryTarget.ALL):
            try:
                out.append(self._decode_reply(key, r, model))
            except RemoteError as exc:
                out.append(exc)
        return out
