"""Key-expression intersection with zenoh's wildcards (``*`` one chunk, ``**`` any number).

Used by the in-memory fake bus; zenoh does this itself for the real one.
"""

from __future__ import annotations

from functools import lru_cache


@lru_cache(maxsize=4096)
def intersects(a: str, b: str) -> bool:
    return _match(tuple(a.split("/")), tuple(b.split("/")))


def _verbatim(chunk: str) -> bool:
    # zenoh: a chunk starting with '@' is verbatim - only the identical chunk matches it.
    return chunk.startswith("@")


def _match(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    if not a:
        return not b or all(c == "**" for c in b)
    if not b:
        return all(c == "**" for c in a)
    if a[0] == "**" and not _verbatim(b[0]):
        return _match(a[1:], b) or _match(a, b[1:])
    if b[0] == "**" and not _verbatim(a[0]):
        return _match(a, b[1:]) or _match(a[1:], b)
    if a[0] == "**" or b[0] == "**":  # a ** facing a verbatim chunk can only match nothing
        return _match(a[1:], b) if a[0] == "**" else _match(a, b[1:])
    if a[0] == b[0] or ((a[0] == "*" or b[0] == "*") and not _verbatim(a[0]) and not _verbatim(b[0])):
        return _match(a[1:], b[1:])
    return False
