"""numba when it is installed, else None: compiled kernels are an accelerator, never a requirement.

Every kernel module imports ``numba`` and ``AVAILABLE`` from here and keeps a numpy path with
identical results for when it is absent.
"""

import contextlib
import os
import threading

try:  # pragma: no cover - which branch runs depends on the environment
    import numba
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.registry import CPUDispatcher

    AVAILABLE = True
except ImportError:  # pragma: no cover
    numba = None
    AVAILABLE = False

try:  # pragma: no cover - POSIX only; elsewhere every process compiles on its own, as numba does
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

__all__ = ["AVAILABLE", "insert_sorted", "kernel", "numba", "one_signature"]


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


def kernel(**options):
    """``numba.njit(nogil=True, cache=True, **options)``, whose first compile of a signature is one process's
    work when several start together on an empty cache: a fresh clone's test workers, services started
    together on a fresh install. numba's on-disk cache alone lets each of them miss, compile the same kernel
    (seconds of CPU for the renderer's) and write it. Here a process takes a file lock beside the cache
    before it looks there, and holds it until it has written what it compiled; the others wait for it and
    then load that, so a waiter idles for the rest of a compile it would otherwise have run whole. A call
    that finds its signature compiled in the process takes no lock."""
    options = {"nogil": True, "cache": True, **options}

    def wrap(fn):
        dispatcher = numba.njit(**options)(fn)
        # numba's decorators build their own Dispatcher class; ours adds one method and no state. (With
        # NUMBA_DISABLE_JIT they return the function itself.)
        if type(dispatcher) is CPUDispatcher:
            dispatcher.__class__ = _CacheLockedDispatcher
        return dispatcher

    return wrap


if AVAILABLE:  # pragma: no cover - which branch runs depends on the environment

    class _CacheLockedDispatcher(CPUDispatcher):
        """numba's dispatcher, with :func:`kernel`'s lock around a compile (which starts with the cache)."""

        _held = threading.local()  # the lock files this thread holds: a kernel's compile may nest another's

        def compile(self, sig):
            # numba's in-process compiler lock first, then the file lock: a thread of this process only ever
            # waits for a file lock while it holds the compiler lock, so two threads never wait on each other.
            with global_compiler_lock, self._cache_lock():
                return super().compile(sig)

        @property
        def cache_lock_path(self) -> str | None:
            """The lock file, beside numba's index of the kernel (named as that is, ``.lock`` for ``.nbi``);
            None without a cache (``cache=False``)."""
            cache_dir = getattr(self._cache, "cache_path", None)
            if cache_dir is None:
                return None
            fn = self.py_func
            name = f"{fn.__module__.rpartition('.')[2]}.{fn.__qualname__}-{fn.__code__.co_firstlineno}.lock"
            return os.path.join(cache_dir, name)

        @contextlib.contextmanager
        def _cache_lock(self):
            held = self._held.__dict__.setdefault("paths", set())
            path = self.cache_lock_path
            if fcntl is None or path is None or path in held:
                yield
                return
            try:
                os.makedirs(os.path.dirname(path), exist_ok=True)
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError:  # a cache numba cannot write either: nothing to share
                yield
                return
            try:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX)
                    held.add(path)
                except OSError:  # a file system without locks: compile on our own, as numba would
                    pass
                yield
            finally:
                held.discard(path)
                os.close(fd)  # releases the lock


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
    insert_sorted = kernel()(insert_sorted)
