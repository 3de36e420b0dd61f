"""Keep large message buffers in the heap instead of fresh ``mmap`` pages (glibc only).

zenoh sends a ``bytes`` payload without copying it and keeps it until the transport is done, so
every 15 MB cloud or 5 MB panorama needs a new buffer. By default glibc serves such sizes with a
fresh ``mmap`` - thousands of page faults per message, which halved cloud throughput on our
2-core machines and made it swing between runs (its threshold adapts to what was freed last).
A fixed, high threshold lets those buffers be reused from the heap. Peak memory is unchanged;
freed memory is returned to the system less eagerly.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_tuned = False


def tune_for_large_messages(threshold_bytes: int = 512 * 1024 * 1024) -> bool:
    """Apply once per process; returns False where the C library is not glibc."""
    global _tuned
    if _tuned:
        return True
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = bool(mallopt(_M_MMAP_THRESHOLD, threshold_bytes)) and bool(mallopt(_M_TRIM_THRESHOLD, threshold_bytes))
    _tuned = ok
    if not ok:
        log.debug("mallopt refused the thresholds")
    return ok
