"""The byte-level port a ROS 2 node needs from zenoh: put/subscribe with attachments, queries and
queryables with attachments, liveliness tokens. The zenoh adapter is
``services/robot_io/ros2_zenoh.py``; core code only sees this interface (and never imports zenoh).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Protocol

from shared.registry import BackendConfig, Registry

# (payload, attachment) -> None; runs on a worker thread, never inside a transport callback.
SampleHandler = Callable[[bytes, bytes | None], None]
# (payload, attachment) -> (reply payload, reply attachment)
QueryHandler = Callable[[bytes, bytes | None], tuple[bytes, bytes | None]]


class Closeable(Protocol):
    def close(self) -> None: ...


class RawPublisher(Protocol):
    def put(self, payload: bytes, attachment: bytes | None = None) -> None: ...

    def close(self) -> None: ...


class TransportError(Exception):
    """The transport failed (no reply, session closed)."""


class Ros2Transport(ABC):
    """One zenoh session, as a ROS 2 context sees it."""

    @property
    @abstractmethod
    def session_id(self) -> str:
        """The session id as rmw_zenoh writes it in liveliness tokens (lowercase hex)."""

    @abstractmethod
    def publisher(self, key: str, *, reliable: bool = True, keep_last: int = 0) -> RawPublisher:
        """``keep_last`` > 0: transient-local as rmw_zenoh does it - the publisher keeps its last
        ``keep_last`` samples and answers a late subscriber's history query with them."""

    @abstractmethod
    def subscribe(self, key: str, handler: SampleHandler, *, max_queue: int = 8,
                  transient_local: bool = False) -> Closeable:
        """Deliver samples on ``key``, in order, on a thread of the subscription's own; when the handler
        falls behind by ``max_queue`` samples the oldest waiting one is dropped, as a ROS 2 keep-last
        queue of that depth does. Transient-local subscriptions (a latched map, a sample or two) drop
        the newest instead: the zenoh adapter's advanced subscriber only takes a callback.
        ``transient_local``: on joining (and whenever a publisher appears later) ask the
        publishers for the samples they keep, so a latched topic (/map) arrives at once."""

    @abstractmethod
    def query(self, key: str, payload: bytes, attachment: bytes | None, timeout_s: float) -> tuple[bytes, bytes | None]:
        """One request; the first ok reply. Raises :class:`TransportError` on no reply or an error reply."""

    @abstractmethod
    def serve(self, key: str, handler: QueryHandler) -> Closeable: ...

    @abstractmethod
    def token(self, key: str) -> Closeable: ...

    @abstractmethod
    def close(self) -> None: ...


TRANSPORTS: Registry[Ros2Transport] = Registry("ros2 transport")


class TransportConfig(BackendConfig):
    """Base of transport configs (the zenoh adapter adds its endpoints)."""
