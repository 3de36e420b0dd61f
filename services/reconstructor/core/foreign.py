"""Clouds in other layouts than ours (other PLY property orders and types, ASCII PLY, extra properties,
PCD), read a chunk at a time from the file on disk (issue 31, item 4): an upload of any size costs one
chunk of memory, not the cloud.

- binary PLY (either endianness) and binary PCD: fixed-size records, read ``_CHUNK_POINTS`` at a time
  with ``np.fromfile(count=)``; elements before the vertices are skipped by size;
- ASCII PLY and ASCII PCD: ``_CHUNK_TEXT_BYTES`` of lines at a time, parsed by numpy's C tokenizer;
- compressed PCD (``binary_compressed``: LZF per field, the whole body one block) and PLYs whose vertices
  come after (or contain) variable-length list properties cannot be cut into records without reading
  it all: :func:`open_foreign` says so (:class:`NotStreamable`) and the caller parses them whole under a
  size limit.

What a chunk holds is what the whole-file parser (open3d, :func:`shared.cloud.read_cloud`) keeps: xyz
and colour, no labels. Colours as that parser gives them for 8-bit channels (the common case); float
channels in [0, 1] are scaled to 0-255 and wider integers clipped to 0-255 (open3d divides every type by
255, which garbles both). Points that are not finite as float32 are dropped by the caller, as there.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.cloud import CloudFormatError, record_chunks

_HEAD_BYTES = 1 << 20  # a header longer than this is not a point cloud we read
_CHUNK_POINTS = 1 << 18  # binary records per chunk: a 256 k chunk of 32-byte records is 8 MB read, ~30 MB of temporaries
_CHUNK_TEXT_BYTES = 4 << 20  # ASCII text per chunk (4 MB of lines; the numbers parsed into about as much)

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8",
              ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}


class NotStreamable(Exception):
    """A valid file that cannot be read record by record (compressed PCD, PLY list properties)."""


@dataclass(frozen=True)
class ForeignLayout:
    """Where the vertex records are and how to read them."""

    kind: str  # "binary" | "ascii"
    count: int  # vertex records
    dtype: np.dtype  # binary: the record; ascii: one float64 column per value (names as the header's)
    body_offset: int  # the first vertex record's byte (binary) / the body's first line (ascii)
    skip_lines: int = 0  # ascii: lines of elements before the vertices
    rgb_packed: str | None = None  # PCD: the packed colour field ("rgb" / "rgba")
    rgb_packed_type: str = "f4"  # its stored type: F (float bits) or U
    float_colours: bool = False  # red/green/blue stored as floats in [0, 1] (scaled to 0-255)

    @property
    def values_per_record(self) -> int:
        return len(self.dtype.names)


def _body_start(head: bytes, marker: bytes) -> tuple[list[str], int]:
    end = head.find(marker)
    if end < 0:
        raise CloudFormatError(f"no {marker.decode().strip()!r} line in the first {_HEAD_BYTES} bytes")
    nl = head.find(b"\n", end + 1)
    if nl < 0:
        raise CloudFormatError("the header has no end")
    return head[:end].decode("ascii", errors="replace").splitlines(), nl + 1


def _ply_layout(head: bytes) -> ForeignLayout:
    if not head.startswith(b"ply"):
        raise CloudFormatError("not a PLY file (no 'ply' magic)")
    lines, body = _body_start(head, b"end_header")
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ") and len(ln.split()) > 1), "")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise CloudFormatError(f"unknown PLY format {fmt!r}")
    elements: list[tuple[str, int, list[tuple[str, str]], bool]] = []  # name, count, props, has a list
    try:
        for ln in lines:
            parts = ln.split()
            if parts[:1] == ["element"]:
                elements.append((parts[1], int(parts[2]), [], False))
                if elements[-1][1] < 0:
                    raise ValueError
            elif parts[:1] == ["property"] and elements:
                name, count, props, has_list = elements[-1]
                if parts[1] == "list":
                    elements[-1] = (name, count, props, True)
                elif parts[1] in _PLY_TYPES:
                    props.append((parts[2], _PLY_TYPES[parts[1]]))
                else:
                    raise CloudFormatError(f"unknown PLY property type {parts[1]!r}")
    except (IndexError, ValueError):
        raise CloudFormatError("malformed PLY header") from None
    at = next((i for i, e in enumerate(elements) if e[0] == "vertex"), None)
    if at is None:
        raise CloudFormatError("the PLY has no vertex element")
    _, count, props, has_list = elements[at]
    if has_list or any(e[3] for e in elements[:at]):
        raise NotStreamable("list properties in or before the vertices")
    names = [n for n, _ in props]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        raise CloudFormatError("the PLY's vertices lack x, y or z (or repeat a property)")
    float_colours = any(t.startswith("f") for n, t in props if n in ("red", "green", "blue"))
    if fmt == "ascii":
        return ForeignLayout("ascii", count, np.dtype([(n, "f8") for n in names]), body,
                             skip_lines=sum(e[1] for e in elements[:at]), float_colours=float_colours)
    order = "<" if fmt == "binary_little_endian" else ">"
    skip = sum(e[1] * np.dtype([(n, order + t) for n, t in e[2]]).itemsize for e in elements[:at])
    return ForeignLayout("binary", count, np.dtype([(n, order + t) for n, t in props]), body + skip,
                         float_colours=float_colours)


def _pcd_layout(head: bytes) -> ForeignLayout:
    lines, body = _body_start(head, b"\nDATA ")
    data_line = head[head.find(b"\nDATA ") + 1:body].decode("ascii", errors="replace").split()
    fields: dict[str, list[str]] = {}
    for ln in lines:
        parts = ln.split()
        if parts and not parts[0].startswith("#"):
            fields[parts[0].upper()] = parts[1:]
    try:
        names = fields["FIELDS"]
        sizes = [int(v) for v in fields["SIZE"]]
        types = fields["TYPE"]
        counts = [int(v) for v in fields.get("COUNT", ["1"] * len(names))]
        points = int(fields["POINTS"][0]) if "POINTS" in fields else (
            int(fields["WIDTH"][0]) * int(fields.get("HEIGHT", ["1"])[0]))
    except (KeyError, IndexError, ValueError):
        raise CloudFormatError("malformed PCD header (FIELDS, SIZE, TYPE, POINTS)") from None
    if not (len(names) == len(sizes) == len(types) == len(counts)) or points < 0 or min(counts, default=1) < 1:
        raise CloudFormatError("malformed PCD header (FIELDS, SIZE, TYPE and COUNT disagree)")
    kind = data_line[1] if len(data_line) > 1 else ""
    if kind == "binary_compressed":
        raise NotStreamable("a compressed PCD is one LZF block")
    if kind not in ("ascii", "binary"):
        raise CloudFormatError(f"unknown PCD DATA {kind!r}")
    cols: list[tuple[str, str]] = []
    packed, packed_type = None, "f4"
    for i, (n, s, t, c) in enumerate(zip(names, sizes, types, counts)):
        try:
            np_type = _PCD_TYPES[(t.upper(), s)]
        except KeyError:
            raise CloudFormatError(f"PCD field {n!r}: unknown type {t}{s}") from None
        if n in ("rgb", "rgba") and c == 1 and s == 4:
            packed, packed_type = n, np_type
        for k in range(c):  # a field of COUNT k is k columns; '_' padding fields get unique names
            cols.append((f"{n}#{i}#{k}" if c > 1 or n == "_" else n, np_type))
    if not {"x", "y", "z"} <= {n for n, _ in cols}:
        raise CloudFormatError("the PCD lacks x, y or z")
    if kind == "ascii":
        return ForeignLayout("ascii", points, np.dtype([(n, "f8") for n, _ in cols]), body,
                             rgb_packed=packed, rgb_packed_type=packed_type)
    return ForeignLayout("binary", points, np.dtype([(n, "<" + t) for n, t in cols]), body,
                         rgb_packed=packed, rgb_packed_type=packed_type)


def layout_of(path: Path) -> ForeignLayout:
    """The layout of a PLY or PCD file from its header; :class:`CloudFormatError` for a malformed one,
    :class:`NotStreamable` for one that must be parsed whole."""
    with open(path, "rb") as fh:
        head = fh.read(_HEAD_BYTES)
    return _ply_layout(head) if path.suffix.lower() == ".ply" else _pcd_layout(head)


def _colours(rec: np.ndarray, layout: ForeignLayout) -> np.ndarray:
    n = len(rec)
    names = rec.dtype.names
    if layout.rgb_packed is not None:
        v = rec[layout.rgb_packed]
        if layout.kind == "ascii":  # the number as printed: its float32 (or integer) bits hold r, g, b
            v = v.astype(np.float32).view(np.uint32) if layout.rgb_packed_type == "f4" else v.astype(np.uint32)
        else:
            v = v.view(np.uint32) if v.dtype.itemsize == 4 else v.astype(np.uint32)
        return np.stack([(v >> 16) & 255, (v >> 8) & 255, v & 255], axis=1).astype(np.uint8)
    if not {"red", "green", "blue"} <= set(names):
        return np.full((n, 3), 128, np.uint8)  # no colour: the whole-file parser's mid grey (0.5)
    out = np.empty((n, 3), np.uint8)
    for i, ch in enumerate(("red", "green", "blue")):
        c = np.nan_to_num(rec[ch].astype(np.float64), nan=0.0)
        if layout.float_colours:
            c = c * 255.0
        out[:, i] = np.clip(np.rint(c), 0, 255).astype(np.uint8)
    return out


def _xyz(rec: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        return np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)


def chunks(path: Path, layout: ForeignLayout) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(xyz float32 (n, 3), rgb uint8 (n, 3))`` a chunk at a time, every record of the file (non-finite
    rows included: the caller drops them); :class:`CloudFormatError` when the body is cut short or
    garbled."""
    if layout.kind == "binary":
        size = path.stat().st_size
        need = layout.body_offset + layout.count * layout.dtype.itemsize
        if size < need:
            raise CloudFormatError(f"truncated file (body holds {size - layout.body_offset} bytes, "
                                   f"{layout.count} records need {need - layout.body_offset})")
        with open(path, "rb") as fh:
            fh.seek(layout.body_offset)
            for _lo, rec in record_chunks(fh, layout.dtype, layout.count, _CHUNK_POINTS, what="the body"):
                yield _xyz(rec), _colours(rec, layout)
        return
    yield from _ascii_chunks(path, layout)


_NON_BLANK = re.compile(rb"\S")


def _ascii_chunks(path: Path, layout: ForeignLayout) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    width = layout.values_per_record
    done = 0
    with open(path, "rb") as fh:
        fh.seek(layout.body_offset)
        skip = layout.skip_lines
        while skip:
            ln = fh.readline()
            if not ln:
                raise CloudFormatError("the body ends before the vertices")
            skip -= bool(_NON_BLANK.search(ln))
        while done < layout.count:
            lines = [ln for ln in fh.readlines(_CHUNK_TEXT_BYTES) if _NON_BLANK.search(ln)]
            if not lines:
                raise CloudFormatError(f"truncated file ({done} records, the header announces {layout.count})")
            lines = lines[: layout.count - done]
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # older numpy warns on a token it cannot read: checked below
                    values = np.fromstring(b" ".join(lines).decode("ascii", errors="replace"), dtype=np.float64,
                                           sep=" ")
            except ValueError:  # numpy 2: a token that is no number
                values = np.empty(0)
            if len(values) != len(lines) * width:
                raise CloudFormatError(f"garbled record near record {done + 1} ({len(values)} numbers in "
                                       f"{len(lines)} lines of {width} values)")
            rec = values.reshape(len(lines), width).view(layout.dtype).reshape(len(lines))
            done += len(lines)
            yield _xyz(rec), _colours(rec, layout)
