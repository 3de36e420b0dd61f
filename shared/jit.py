"""numba when it is installed, else None: compiled kernels are an accelerator, never a requirement.

Every kernel module imports ``numba`` and ``AVAILABLE`` from here and keeps a numpy path with
identical results for when it is absent.
"""

import threading

try:  # pragma: no cover - which branch runs depends on the environment
    import numba

    AVAILABLE = True
except ImportError:  # pragma: no cover
    numba = None
    AVAILABLE = False

__all__ = ["AVAILABLE", "insert_sorted", "numba", "one_signature"]


class one_signature:  # noqa: N801 - used like numba's own decorators
    """A jitted kernel compiled for one signature only: the types of its first call, with every array
    argument taken as any layout (numba's ``'A'``). numba otherwise compiles a new machine code for each
    layout an argument arrives in: a strided column view and a contiguous array of the same dtype are two
    signatures. ``visibility_kernels.finish`` was compiled four times (3.5 s of CPU each on a cold cache:
    a fresh clone's first test run, in every process that renders) for one call site whose renderer paths
    pass views or copies. Later calls of the same dtypes and ranks run that code (numba converts any layout
    to ``'A'``, and a writable array to a read-only one). Any other dtype or rank, or a read-only array
    where the first call's was writable, is a ``TypeError``, not a silent recompile: the caller keeps
    them fixed.

    ``read_only``: the positions of array arguments the kernel only reads, typed read-only whatever the
    first call passes, so that a caller with a read-only array (a panorama's depth) and one with a
    writable copy share the signature, whichever of them comes first."""

    def __init__(self, dispatcher, read_only: tuple[int, ...] = ()):
        self._dispatcher = dispatcher
        self._read_only = frozenset(read_only)
        self._lock = threading.Lock()
        self._typed = False

    @property
    def signatures(self):
        return self._dispatcher.signatures

    def __call__(self, *args):
        if not self._typed:
            with self._lock:  # render threads may make the first call together
                if not self._typed:
                    types = tuple(self._any_layout(i, numba.typeof(a)) for i, a in enumerate(args))
                    self._dispatcher.compile(types)  # or loaded from numba's cache (cache=True)
                    self._dispatcher.disable_compile()
                    self._typed = True
        return self._dispatcher(*args)

    def _any_layout(self, i, t):
        if not isinstance(t, numba.types.Array):
            return t
        return t.copy(layout="A", readonly=not t.mutable or i in self._read_only)


def insert_sorted(buf, n, x):  # pragma: no cover - called from compiled kernels
    """``x`` inserted into ``buf[:n]``, kept ascending (an insertion sort's step); returns the new count.

    The gated depth medians of a sensor that declares its noise (the waypoint predictor's column
    median, the reconstructor's denoising) sort a handful of neighbours per pixel: a few compares,
    where a call to a general sort would cost more than the sorting."""
    j = n
    while j > 0 and buf[j - 1] > x:
        buf[j] = buf[j - 1]
        j -= 1
    buf[j] = x
    return n + 1


if AVAILABLE:  # pragma: no cover - which branch runs depends on the environment
    insert_sorted = numba.njit(nogil=True, cache=True)(insert_sorted)
