"""Bad payloads for the bus: malformed, truncated, wrong-schema, wrong-version, invalid and oversized.

Every payload made here must be refused by any queryable or subscriber of the system, whatever its
request schema: none is a valid request of any schema (truncation cuts into the header, invalid data
carries a field no message allows, ...), so a fuzzed request can never move the robot or start work.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

import msgpack
import numpy as np

from shared.codec import MAGIC, encode
from shared.schemas import (
    CameraIntrinsics, MapRequest, MoveRequest, Ping, Pose, RenderRequest, ViewPose,
)

_HEAD = struct.Struct("<4sI")
CATEGORIES = ("malformed", "truncated", "wrong_schema", "wrong_version", "invalid", "lying_arrays", "oversized")


def _samples() -> list:
    """Valid messages of several schemas (with and without arrays) to corrupt."""
    return [
        Ping(), MoveRequest(dx_m=0.5, dy_m=0.0), MapRequest(map_id="m"), Pose(position_m=(0, 0, 0)),
        RenderRequest(map_id="m", views=[ViewPose(position_m=(0, 0, 1.25), heading_rad=0.0)],
                      camera=CameraIntrinsics()),
    ]


def _envelope(header: dict, tail: bytes = b"") -> bytes:
    packed = msgpack.packb(header, use_bin_type=True)
    return _HEAD.pack(MAGIC, len(packed)) + packed + tail


def _header_of(payload: bytes) -> tuple[dict, int]:
    _, n = _HEAD.unpack_from(payload, 0)
    return msgpack.unpackb(payload[_HEAD.size:_HEAD.size + n], raw=False, strict_map_key=False), _HEAD.size + n


def bad_payloads(request_schema: str, n: int, seed: int, *, oversized_bytes: int = 4 << 20) -> Iterator[tuple[str, bytes]]:
    """``n`` bad payloads for a queryable whose request schema is ``request_schema``, cycling the categories."""
    rng = np.random.default_rng(seed)
    samples = _samples()
    others = [m for m in samples if m.SCHEMA != request_schema]
    for i in range(n):
        cat = CATEGORIES[i % len(CATEGORIES)]
        msg = samples[int(rng.integers(len(samples)))]
        if cat == "malformed":
            kind = i // len(CATEGORIES) % 4
            if kind == 0:
                out = rng.bytes(int(rng.integers(0, 512)))
            elif kind == 1:  # our magic, a length, then garbage
                out = MAGIC + struct.pack("<I", int(rng.integers(0, 64))) + rng.bytes(64)
            elif kind == 2:  # valid msgpack, not a header
                out = _envelope({"s": 1}) if rng.random() < 0.5 else _HEAD.pack(MAGIC, 3) + msgpack.packb([1, 2])
            else:  # a header whose arrays table is nonsense
                out = _envelope({"s": request_schema, "v": 1, "d": {"__nd__": 5}, "a": [["<f4", [-1], 0, 4]]})
        elif cat == "truncated":
            payload = encode(msg)
            _, head_end = _header_of(payload)
            out = payload[: int(rng.integers(0, head_end))]  # always cuts into the header
        elif cat == "wrong_schema":
            out = encode(others[int(rng.integers(len(others)))])
            if rng.random() < 0.3:  # or a schema nobody has
                header, head_end = _header_of(out)
                header["s"] = "NoSuchSchema"
                out = _envelope(header, out[head_end:])
        elif cat == "wrong_version":
            header, head_end = _header_of(encode(msg))
            header["s"] = request_schema
            header["v"] = int(rng.choice([0, 2, 99, -1, 2**31]))
            out = _envelope(header)
        elif cat == "invalid":  # the right schema and version, data no model accepts
            data = {"__bogus__": 1} if rng.random() < 0.5 else [1, 2, 3]
            out = _envelope({"s": request_schema, "v": 1, "d": data, "a": []})
        elif cat == "lying_arrays":  # an array table that claims more data than the payload holds
            nbytes = int(rng.choice([4, 1 << 20, 1 << 40]))
            out = _envelope({"s": request_schema, "v": 1, "d": {"__bogus__": {"__nd__": 0}},
                             "a": [["<f4", [nbytes // 4], 0, nbytes]]})
        else:  # oversized: a large payload of junk behind a valid-looking header
            out = _envelope({"s": request_schema, "v": 1, "d": {"__bogus__": {"__nd__": 0}},
                             "a": [["|u1", [oversized_bytes], 0, oversized_bytes]]}, b"\0" * (oversized_bytes + 8))
        yield cat, out
