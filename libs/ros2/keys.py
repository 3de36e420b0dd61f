"""How ROS 2 names become zenoh key expressions: the ``bridge`` and ``rmw_zenoh`` key styles.

* ``bridge`` (zenoh-bridge-ros2dds): a topic or service is the key of its ROS name without the
  leading slash, under an optional prefix (the bridge's ``namespace`` option). Payloads are CDR; no
  attachment, no graph tokens (the bridge does DDS discovery itself).
* ``rmw_zenoh`` (ros2/rmw_zenoh ``docs/design.md``): ``<domain_id>/<fully_qualified_name>/<DDS type
  name>/<RIHS01 type hash>``; every publication, request and reply carries the 33-byte attachment
  (sequence number, source timestamp, GID); every node, publisher, subscription, service server and
  client holds a liveliness token under the hermetic ``@ros2_lv`` prefix so that ``ros2 topic list``
  on the robot sees it.

Pure: no zenoh import. The transport adapter moves bytes; this module decides the bytes and keys.
"""

from __future__ import annotations

import hashlib
import re
import struct
import time
from dataclasses import dataclass
from enum import StrEnum

from .errors import Ros2ProtocolError
from .messages import RosType

LIVELINESS_PREFIX = "@ros2_lv"
ATTACHMENT_SIZE = 8 + 8 + 1 + 16
GID_SIZE = 16

_NAME_RE = re.compile(r"^/?[A-Za-z_~][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


class RosNameError(Ros2ProtocolError, ValueError):
    """Not a valid ROS 2 topic/service/node name."""


class EntityKind(StrEnum):
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


def fully_qualified(name: str, namespace: str = "") -> str:
    """``/ns/name`` for a relative name, ``name`` itself when absolute (ROS 2 name resolution)."""
    if not _NAME_RE.match(name):
        raise RosNameError(f"not a valid ROS 2 name: {name!r}")
    if name.startswith("/"):
        return name
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{name}"


def mangle(name: str) -> str:
    """rmw_zenoh's mangling of a name inside one liveliness chunk: every ``/`` becomes ``%``."""
    return name.replace("/", "%") if name else "%"


@dataclass(frozen=True)
class Qos:
    """The QoS of an entity; rmw_zenoh's defaults are RELIABLE, VOLATILE, KEEP_LAST 42."""

    reliable: bool = True
    transient_local: bool = False
    keep_all: bool = False
    depth: int = 10

    def keyexpr(self) -> str:
        """rmw_zenoh's ``qos_to_keyexpr``: 11 fields, each empty when it is the default:
        ``<rel>:<dur>:<hist>,<depth>:<dl_s>,<dl_ns>:<ls_s>,<ls_ns>:<liv>,<lease_s>,<lease_ns>``
        (enum values of rmw_qos_*_policy_e: BEST_EFFORT 2, TRANSIENT_LOCAL 1, KEEP_ALL 2)."""
        rel = "" if self.reliable else "2"
        dur = "1" if self.transient_local else ""
        hist = "2" if self.keep_all else ""
        depth = "" if self.depth == 42 else str(self.depth)
        return f"{rel}:{dur}:{hist},{depth}:,:,:,,"


@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh's attachment: int64 LE sequence number, int64 LE source timestamp (ns since the
    UNIX epoch), one byte GID length (16), the 16-byte GID of the publisher or client."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(self.gid)}")
        return struct.pack("<qqB", self.sequence_number, self.source_timestamp_ns, GID_SIZE) + self.gid

    @classmethod
    def decode(cls, data: bytes | None) -> Attachment:
        if data is None or len(data) < 17:
            raise RosNameError(f"an rmw_zenoh attachment has {ATTACHMENT_SIZE} bytes, got {0 if data is None else len(data)}")
        seq, ts, n = struct.unpack_from("<qqB", data, 0)
        if n != GID_SIZE or len(data) != 17 + n:
            raise RosNameError(f"attachment GID length {n} with {len(data)} bytes in all")
        return cls(seq, ts, bytes(data[17:17 + n]))


def gid_for(token_key: str) -> bytes:
    """A stable 16-byte GID per entity (rmw_zenoh hashes the entity too; any unique 16 bytes do)."""
    return hashlib.sha256(token_key.encode()).digest()[:GID_SIZE]


class KeyStyle:
    """Topic/service keys, and whether attachments and graph tokens are part of the protocol."""

    name = ""
    attachments = False

    def topic_key(self, name: str, rtype: RosType) -> str:
        raise NotImplementedError

    def service_key(self, name: str, rtype: RosType) -> str:
        return self.topic_key(name, rtype)

    def node_token(self, session_id: str, node_id: int, node: str) -> str | None:
        return None

    def entity_token(self, session_id: str, node_id: int, entity_id: int, kind: EntityKind, node: str,
                     name: str, rtype: RosType, qos: Qos) -> str | None:
        return None


@dataclass(frozen=True)
class BridgeKeys(KeyStyle):
    """zenoh-bridge-ros2dds: ``[prefix/]name`` (the ROS name without its leading slash)."""

    prefix: str = ""
    namespace: str = ""
    name = "bridge"
    attachments = False

    def topic_key(self, name: str, rtype: RosType) -> str:
        fq = fully_qualified(name, self.namespace).lstrip("/")
        p = self.prefix.strip("/")
        return f"{p}/{fq}" if p else fq


@dataclass(frozen=True)
class RmwZenohKeys(KeyStyle):
    """rmw_zenoh: ``<domain>/<fq name>/<DDS type>/<RIHS01 hash>`` + attachments + liveliness tokens."""

    domain_id: int = 0
    namespace: str = ""
    enclave: str = ""
    name = "rmw_zenoh"
    attachments = True

    def __post_init__(self):
        if not 0 <= self.domain_id <= 232:  # ROS_DOMAIN_ID range
            raise RosNameError(f"ROS domain id out of range 0..232: {self.domain_id}")

    def topic_key(self, name: str, rtype: RosType) -> str:
        fq = fully_qualified(name, self.namespace).lstrip("/")
        return f"{self.domain_id}/{fq}/{rtype.dds_name}/{rtype.type_hash}"

    def _node_part(self, node: str) -> str:
        ns = "/" + self.namespace.strip("/") if self.namespace.strip("/") else ""
        return f"{mangle(self.enclave)}/{mangle(ns)}/{node}"

    def node_token(self, session_id: str, node_id: int, node: str) -> str:
        return f"{LIVELINESS_PREFIX}/{self.domain_id}/{session_id}/{node_id}/{node_id}/{EntityKind.NODE}/{self._node_part(node)}"

    def entity_token(self, session_id: str, node_id: int, entity_id: int, kind: EntityKind, node: str,
                     name: str, rtype: RosType, qos: Qos) -> str:
        fq = fully_qualified(name, self.namespace)
        return (f"{LIVELINESS_PREFIX}/{self.domain_id}/{session_id}/{node_id}/{entity_id}/{kind}/{self._node_part(node)}/"
                f"{mangle(fq)}/{rtype.dds_name}/{rtype.type_hash}/{qos.keyexpr()}")


class KeyStyleName(StrEnum):
    BRIDGE = "bridge"
    RMW_ZENOH = "rmw_zenoh"


def key_style(style: str, *, domain_id: int = 0, namespace: str = "", prefix: str = "") -> KeyStyle:
    """The key style by name (``bridge`` | ``rmw_zenoh``), as configured."""
    table = {
        KeyStyleName.BRIDGE: lambda: BridgeKeys(prefix=prefix, namespace=namespace),
        KeyStyleName.RMW_ZENOH: lambda: RmwZenohKeys(domain_id=domain_id, namespace=namespace),
    }
    try:
        return table[KeyStyleName(style)]()
    except ValueError:
        raise RosNameError(f"unknown key style {style!r}; known: bridge, rmw_zenoh") from None


def now_ns() -> int:
    return time.time_ns()
