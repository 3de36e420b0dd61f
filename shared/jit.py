"""numba when it is installed, else None: compiled kernels are an accelerator, never a requirement.

Every kernel module imports ``numba`` and ``AVAILABLE`` from here and keeps a numpy path with
identical results for when it is absent.
"""

try:  # pragma: no cover - which branch runs depends on the environment
    import numba

    AVAILABLE = True
except ImportError:  # pragma: no cover
    numba = None
    AVAILABLE = False

__all__ = ["AVAILABLE", "numba"]
