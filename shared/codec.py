"""Binary codec for bus messages.

Layout of one payload::

    b"ANT1" | u32 header_len | msgpack header | padding | array 0 bytes | padding | array 1 bytes ...

The msgpack header is ``{"s": schema, "v": version, "d": data, "a": [[dtype, shape, offset, nbytes], ...]}``
where every numpy array inside ``data`` was replaced by ``{"__nd__": i}``. Arrays travel *out of band*,
8-byte aligned, so a receiver builds them with ``np.frombuffer`` straight over the received buffer:
no copy on decode (the arrays are read-only views; copy before writing). The encoder makes exactly one
copy of each array, into the output buffer.

Every problem with a payload - not ours, truncated, malformed msgpack, wrong schema or version, a
field that fails validation, over the size limit - raises :class:`CodecError`, so a service needs one
``except`` to turn bad input into a typed error reply.
"""

from __future__ import annotations

import struct
from typing import Any, TypeVar

import msgpack
import numpy as np
from pydantic import ValidationError

from shared.schemas import Message

MAGIC = b"ANT1"
_HEADER = struct.Struct("<4sI")
_ALIGN = 8
DEFAULT_MAX_BYTES = 512 * 1024 * 1024
# dtypes a message may carry; anything else (object arrays above all) is refused on both sides.
_ALLOWED_DTYPES = {
    np.dtype(t).str
    for t in ("bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "int64", "uint64",
              "float16", "float32", "float64")
}

M = TypeVar("M", bound=Message)


class CodecError(ValueError):
    """A payload could not be encoded or decoded; ``reason`` is a short machine-readable tag."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def _strip_arrays(obj: Any, arrays: list[np.ndarray]) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.str not in _ALLOWED_DTYPES:
            raise CodecError("unsupported_dtype", f"cannot send arrays of dtype {obj.dtype}")
        arrays.append(obj)
        return {"__nd__": len(arrays) - 1}
    if isinstance(obj, dict):
        return {k: _strip_arrays(v, arrays) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strip_arrays(v, arrays) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def encode(msg: Message) -> bytes:
    """Encode a message into one contiguous payload."""
    arrays: list[np.ndarray] = []
    data = _strip_arrays(msg.model_dump(mode="python"), arrays)
    table = []
    offset = 0
    for arr in arrays:
        offset = -(-offset // _ALIGN) * _ALIGN
        table.append([arr.dtype.str, list(arr.shape), offset, arr.nbytes])
        offset += arr.nbytes
    try:
        header = msgpack.packb(
            {"s": msg.SCHEMA, "v": msg.VERSION, "d": data, "a": table}, use_bin_type=True
        )
    except (TypeError, ValueError, OverflowError) as exc:
        raise CodecError("unencodable", str(exc)) from exc
    head_end = _HEADER.size + len(header)
    start = -(-head_end // _ALIGN) * _ALIGN
    # bytes.join copies each array's buffer exactly once, straight into the final immutable payload
    # (no zero-filled scratch buffer), and zenoh wraps an immutable bytes object without copying it.
    parts: list = [_HEADER.pack(MAGIC, len(header)), header, b"\0" * (start - head_end)]
    pos = 0
    for arr, (_, _, off, nbytes) in zip(arrays, table):
        if off > pos:
            parts.append(b"\0" * (off - pos))
        if nbytes:
            parts.append(memoryview(np.ascontiguousarray(arr)).cast("B"))
        pos = off + nbytes
    return b"".join(parts)


def _restore_arrays(obj: Any, arrays: list[np.ndarray]) -> Any:
    if isinstance(obj, dict):
        if len(obj) == 1 and "__nd__" in obj:
            idx = obj["__nd__"]
            if not isinstance(idx, int) or not 0 <= idx < len(arrays):
                raise CodecError("malformed", f"bad array reference {idx!r}")
            return arrays[idx]
        return {k: _restore_arrays(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_restore_arrays(v, arrays) for v in obj]
    return obj


def peek(payload: bytes | bytearray | memoryview, max_bytes: int = DEFAULT_MAX_BYTES):
    """Parse the envelope: returns (schema, version, data-with-arrays). No model validation."""
    buf = memoryview(payload)
    if buf.nbytes > max_bytes:
        raise CodecError("oversized", f"{buf.nbytes} bytes > limit {max_bytes}")
    if buf.nbytes < _HEADER.size:
        raise CodecError("truncated", f"{buf.nbytes} bytes is shorter than the envelope header")
    magic, header_len = _HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise CodecError("not_ours", "payload does not start with the SpatialAnt magic")
    if _HEADER.size + header_len > buf.nbytes:
        raise CodecError("truncated", "header runs past the end of the payload")
    try:
        header = msgpack.unpackb(
            buf[_HEADER.size : _HEADER.size + header_len], raw=False, strict_map_key=False,
        )
    except Exception as exc:  # msgpack raises several unrelated types
        raise CodecError("malformed", f"header is not valid msgpack ({exc})") from exc
    if not isinstance(header, dict) or not {"s", "v", "d", "a"} <= header.keys():
        raise CodecError("malformed", "header lacks schema/version/data/arrays")
    start = -(-(_HEADER.size + header_len) // _ALIGN) * _ALIGN
    arrays = []
    try:
        for dtype_str, shape, off, nbytes in header["a"]:
            if dtype_str not in _ALLOWED_DTYPES:
                raise CodecError("malformed", f"array dtype {dtype_str!r} not allowed")
            dtype = np.dtype(dtype_str)
            shape = tuple(int(s) for s in shape)
            if any(s < 0 for s in shape) or int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != nbytes:
                raise CodecError("malformed", f"array shape {shape} does not match {nbytes} bytes")
            if off < 0 or start + off + nbytes > buf.nbytes:
                raise CodecError("truncated", "array data runs past the end of the payload")
            arrays.append(
                np.frombuffer(buf, dtype=dtype, count=nbytes // dtype.itemsize, offset=start + off)
                .reshape(shape)
            )
    except CodecError:
        raise
    except (TypeError, ValueError) as exc:
        raise CodecError("malformed", f"bad array table ({exc})") from exc
    return header["s"], header["v"], _restore_arrays(header["d"], arrays)


def decode(payload: bytes | bytearray | memoryview, model: type[M], max_bytes: int = DEFAULT_MAX_BYTES) -> M:
    """Decode a payload into ``model``; any problem raises :class:`CodecError`."""
    schema, version, data = peek(payload, max_bytes)
    if schema != model.SCHEMA:
        raise CodecError("wrong_schema", f"expected {model.SCHEMA}, got {schema!r}")
    if version != model.VERSION:
        raise CodecError("wrong_version", f"{model.SCHEMA} v{model.VERSION} expected, got v{version!r}")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        errors = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or '<root>'}: {e['msg']}" for e in exc.errors()[:5]
        )
        raise CodecError("invalid", f"{model.SCHEMA}: {errors}") from exc


def decode_any(payload, models: dict[str, type[Message]], max_bytes: int = DEFAULT_MAX_BYTES) -> Message:
    """Decode a payload that may be one of several schemas (e.g. a result or an ErrorReply)."""
    schema, _, _ = peek(payload, max_bytes)
    if schema not in models:
        raise CodecError("wrong_schema", f"expected one of {sorted(models)}, got {schema!r}")
    return decode(payload, models[schema], max_bytes)
