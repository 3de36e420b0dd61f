"""A ROS 2 node over a :class:`Ros2Transport`: typed publishers, subscriptions, service clients and
servers, in either key style. Shared by the ``ros2`` robot backend and the stand-in robot, so both
ends of every test speak exactly the same protocol.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from . import messages as m
from .keys import Attachment, EntityKind, KeyStyle, Qos, gid_for
from .transport import Closeable, Ros2Transport, TransportError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Received:
    """Metadata of a received message: local receive time, and rmw_zenoh's attachment when present."""

    received_s: float  # time.monotonic() at receipt
    attachment: Attachment | None


class Publisher:
    def __init__(self, node: Ros2Node, name: str, rtype: m.RosType, qos: Qos):
        self.node, self.name, self.rtype = node, name, rtype
        self.key = node.keys.topic_key(name, rtype)
        # A transient-local publisher keeps its last ``depth`` samples for subscribers that join later.
        self._raw = node.transport.publisher(self.key, reliable=qos.reliable,
                                             keep_last=max(1, qos.depth) if qos.transient_local else 0)
        self._token_key = node._declare(EntityKind.PUBLISHER, name, rtype, qos)
        self.gid = gid_for(self._token_key or self.key)
        self._seq = itertools.count(1)
        self._lock = threading.Lock()

    def publish(self, msg: Any) -> None:
        self.publish_raw(m.encode(self.rtype.name, msg))

    def publish_raw(self, payload: bytes) -> None:
        att = None
        with self._lock:  # sequence numbers in the order of publication
            if self.node.keys.attachments:
                att = Attachment(next(self._seq), time.time_ns(), self.gid).encode()
            self._raw.put(payload, att)

    def close(self) -> None:
        self._raw.close()


class Ros2Node:
    """One ROS 2 node: owns its entities and their liveliness tokens; ``close`` removes them all."""

    def __init__(self, transport: Ros2Transport, keys: KeyStyle, name: str = "spatialant"):
        self.transport, self.keys, self.name = transport, keys, name
        self._ids = itertools.count(1)
        self._owned: list[Closeable] = []
        self.node_id = 0
        tok = keys.node_token(transport.session_id, self.node_id, name)
        if tok:
            self._owned.append(transport.token(tok))
        self.decode_errors = 0

    def _declare(self, kind: EntityKind, name: str, rtype: m.RosType, qos: Qos) -> str | None:
        key = self.keys.entity_token(self.transport.session_id, self.node_id, next(self._ids), kind, self.name,
                                     name, rtype, qos)
        if key:
            self._owned.append(self.transport.token(key))
        return key

    def publisher(self, name: str, type_name: str, qos: Qos = Qos()) -> Publisher:
        pub = Publisher(self, name, m.RosType(type_name), qos)
        self._owned.append(pub)
        return pub

    def subscribe(self, name: str, type_name: str, handler: Callable[[Any, Received], None], qos: Qos = Qos(),
                  *, max_queue: int = 4) -> Closeable:
        rtype = m.RosType(type_name)
        key = self.keys.topic_key(name, rtype)

        def on_sample(payload: bytes, attachment: bytes | None) -> None:
            t = time.monotonic()
            try:
                msg = m.decode(type_name, payload)
                att = Attachment.decode(attachment) if attachment is not None else None
            except Exception as exc:  # a stranger on our key must not kill the subscription
                self.decode_errors += 1
                log.warning("dropped a bad %s on %s: %s", type_name, key, exc)
                return
            handler(msg, Received(t, att))

        sub = self.transport.subscribe(key, on_sample, max_queue=max_queue, transient_local=qos.transient_local)
        self._declare(EntityKind.SUBSCRIPTION, name, rtype, qos)
        self._owned.append(sub)
        return sub

    def client(self, name: str, type_name: str) -> ServiceClient:
        return ServiceClient(self, name, m.RosType(type_name))

    def serve(self, name: str, type_name: str, handler: Callable[[Any], Any]) -> Closeable:
        rtype = m.RosType(type_name)
        key = self.keys.service_key(name, rtype)

        def on_query(payload: bytes, attachment: bytes | None) -> tuple[bytes, bytes | None]:
            req = m.decode(f"{type_name}_Request", payload)
            resp = handler(req)
            att = None
            if self.keys.attachments:
                # The reply echoes the request's sequence number and client GID (design.md).
                a = Attachment.decode(attachment)
                att = Attachment(a.sequence_number, time.time_ns(), a.gid).encode()
            return m.encode(f"{type_name}_Response", resp), att

        srv = self.transport.serve(key, on_query)
        self._declare(EntityKind.SERVICE, name, rtype, Qos())
        self._owned.append(srv)
        return srv

    def close(self) -> None:
        for o in reversed(self._owned):
            try:
                o.close()
            except Exception:
                log.debug("close failed", exc_info=True)
        self._owned.clear()


class ServiceClient:
    def __init__(self, node: Ros2Node, name: str, rtype: m.RosType):
        self.node, self.name, self.rtype = node, name, rtype
        self.key = node.keys.service_key(name, rtype)
        token = node._declare(EntityKind.CLIENT, name, rtype, Qos())
        self.gid = gid_for(token or self.key)
        self._seq = itertools.count(1)

    def call(self, request: Any, timeout_s: float = 5.0) -> Any:
        seq = next(self._seq)
        att = Attachment(seq, time.time_ns(), self.gid).encode() if self.node.keys.attachments else None
        payload, ratt = self.node.transport.query(self.key, m.encode(f"{self.rtype.name}_Request", request), att, timeout_s)
        if self.node.keys.attachments:
            a = Attachment.decode(ratt)
            if a.sequence_number != seq or a.gid != self.gid:
                raise TransportError(f"reply on {self.name} for request {a.sequence_number}, not {seq}")
        return m.decode(f"{self.rtype.name}_Response", payload)
