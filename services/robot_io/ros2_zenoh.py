"""The zenoh adapter of the ROS 2 transport port (``core/ros2/transport.py``).

Registered as transport ``zenoh``; importing this module is what makes the ``ros2`` robot backend
usable (the service and the stand-in import it). One zenoh session per robot connection, built by
the one config builder (``shared.bus.config.zenoh_config``).
"""

from __future__ import annotations

import logging
import threading

import zenoh
import zenoh.ext
from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from libs.ros2.transport import (
    TRANSPORTS, QueryHandler, Ros2Transport, SampleHandler, TransportConfig, TransportError,
)
from shared.bus.base import Dispatcher, Overloaded
from shared.bus.config import ZenohSettings, zenoh_config

log = logging.getLogger(__name__)


class BusEnv(BaseSettings):
    """The process's ``ANT_ZENOH__*`` environment, read as the services read it (shared/runner.py)."""

    model_config = SettingsConfigDict(env_prefix="ANT_", env_nested_delimiter="__", extra="ignore")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)


def env_zenoh_settings() -> ZenohSettings:
    """How this process joins its bus: robot-io's ROS 2 session, unless configured otherwise, goes
    where robot-io itself goes, as robot-io (on an authenticated bus its ACL grants the ROS 2 keys)."""
    return BusEnv().zenoh


LOOPBACK_LISTEN = "tcp/127.0.0.1:0"


def loopback_unless_told(settings: ZenohSettings) -> ZenohSettings:
    """A peer or router told no ``listen`` endpoint listens on loopback only (a free port), not on
    every interface as zenoh's default ``tcp/[::]:0`` does: a robot's topics (and its cmd_vel)
    reach another host only when someone asks for it with ``listen`` or ``connect``. A client
    listens on nothing anyway."""
    if settings.mode == "client" or settings.listen:
        return settings
    return settings.model_copy(update={"listen": [LOOPBACK_LISTEN]})


def ros2_zenoh_config(settings: ZenohSettings):
    """The session config of a ROS 2 context: loopback unless told, and timestamping on, as
    rmw_zenoh's default config has it: the advanced publisher of a transient-local topic orders
    its cached samples by timestamp and refuses to start without."""
    conf = zenoh_config(loopback_unless_told(settings))
    conf.insert_json5("timestamping/enabled", "true")
    return conf


class ZenohTransportConfig(TransportConfig):
    zenoh: ZenohSettings = Field(default_factory=env_zenoh_settings,
                                 description="how to reach the robot's zenoh network (default: the service's bus)")


class _Closer:
    def __init__(self, *fns):
        self._fns, self._lock, self._done = fns, threading.Lock(), False

    def close(self) -> None:
        with self._lock:
            if self._done:
                return
            self._done = True
        for fn in self._fns:
            try:
                fn()
            except Exception:
                log.debug("undeclare failed", exc_info=True)


class _Pub:
    def __init__(self, pub):
        self._pub = pub

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        if attachment is None:
            self._pub.put(payload)
        else:
            self._pub.put(payload, attachment=attachment)

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except Exception:
            pass


@TRANSPORTS.register("zenoh", ZenohTransportConfig)
class ZenohRos2Transport(Ros2Transport):
    def __init__(self, config: ZenohTransportConfig | None = None, *, session: zenoh.Session | None = None):
        self.config = config or ZenohTransportConfig()
        self.session = session or zenoh.open(ros2_zenoh_config(self.config.zenoh))
        self._owns_session = session is None
        self._sid = str(self.session.info.zid())

    @property
    def session_id(self) -> str:
        return self._sid

    def publisher(self, key: str, *, reliable: bool = True, keep_last: int = 0):
        # DROP, not BLOCK: a stalled robot link must never block the control loop's stop command.
        qos = {"congestion_control": zenoh.CongestionControl.DROP,
               "reliability": zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT}
        if keep_last > 0:
            # rmw_zenoh's transient-local (docs/design.md, "Durability"): an advanced publisher whose
            # cache holds the last ``depth`` samples and answers history queries, and that announces
            # itself (publisher_detection) so subscribers already listening learn it is there.
            return _Pub(zenoh.ext.declare_advanced_publisher(
                self.session, key, cache=zenoh.ext.CacheConfig(max_samples=keep_last), publisher_detection=True,
                **qos))
        return _Pub(self.session.declare_publisher(key, **qos))

    def subscribe(self, key: str, handler: SampleHandler, *, max_queue: int = 8, transient_local: bool = False):
        if not transient_local:
            return self._pumped(key, handler, max_queue)
        disp = Dispatcher(f"ros2:{key}", 1, max_queue)

        def on_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            att = sample.attachment.to_bytes() if sample.attachment is not None else None
            try:
                disp.submit(lambda: handler(payload, att))
            except Overloaded:
                pass  # sensor streams: the newest sample is dropped while the worker is behind

        # rmw_zenoh's transient-local subscription: an advanced subscriber that queries the
        # publishers' caches on joining, and again for each publisher detected later.
        sub = zenoh.ext.declare_advanced_subscriber(
            self.session, key, on_sample, history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
        return _Closer(sub.undeclare, disp.close)

    def _pumped(self, key: str, handler: SampleHandler, max_queue: int):
        """A subscription whose samples wait in zenoh's own ring buffer (the oldest is overwritten when
        full, as a ROS 2 keep-last queue does) for one thread that takes them out and handles them.

        A callback handing each sample to a worker queue woke two threads per sample (zenoh's, to take
        the GIL, and the worker): at a stand-in's 1,200 messages a second that was most of robot-io's
        CPU while it only listened. Here zenoh's thread never takes the GIL and one thread wakes."""
        sub = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(max(1, max_queue)))
        rx = sub.handler

        def pump(_keep=sub) -> None:  # a channel subscriber dropped is undeclared: the thread holds it
            while True:
                try:
                    sample = rx.recv()  # releases the GIL while it waits
                except zenoh.ZError:
                    return  # undeclared: the channel is closed and empty
                att = sample.attachment.to_bytes() if sample.attachment is not None else None
                try:
                    handler(sample.payload.to_bytes(), att)
                except Exception:  # a handler bug must not end the subscription
                    log.exception("handler for %s failed", key)

        thread = threading.Thread(target=pump, name=f"ros2:{key}", daemon=True)
        thread.start()

        def join() -> None:
            if thread is not threading.current_thread():
                thread.join(2.0)

        return _Closer(sub.undeclare, join)

    def query(self, key: str, payload: bytes, attachment: bytes | None, timeout_s: float):
        kwargs = {"payload": payload, "timeout": timeout_s, "target": zenoh.QueryTarget.ALL_COMPLETE}
        if attachment is not None:
            kwargs["attachment"] = attachment
        for r in self.session.get(key, **kwargs):
            if r.ok is not None:
                att = r.ok.attachment.to_bytes() if r.ok.attachment is not None else None
                return r.ok.payload.to_bytes(), att
            raise TransportError(f"{key}: {r.err.payload.to_string()}")
        raise TransportError(f"no reply on {key} within {timeout_s:.1f} s")

    def serve(self, key: str, handler: QueryHandler):
        disp = Dispatcher(f"ros2-srv:{key}", 1, 16)

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            att = query.attachment.to_bytes() if query.attachment is not None else None

            def job():
                try:
                    out, ratt = handler(payload, att)
                    if ratt is None:
                        query.reply(key, out)
                    else:
                        query.reply(key, out, attachment=ratt)
                except Exception as exc:
                    log.warning("service %s failed: %s", key, exc)
                    query.reply_err(f"{type(exc).__name__}: {exc}".encode())
                finally:
                    query.drop()

            try:
                disp.submit(job)
            except Overloaded:
                query.reply_err(b"overloaded")
                query.drop()

        q = self.session.declare_queryable(key, on_query, complete=True)
        return _Closer(q.undeclare, disp.close)

    def token(self, key: str):
        tok = self.session.liveliness().declare_token(key)
        return _Closer(tok.undeclare)

    def close(self) -> None:
        if self._owns_session:
            try:
                self.session.close()
            except Exception:
                log.debug("session close failed", exc_info=True)
