"""shared.jit.one_signature: a kernel compiled once for the layouts its callers pass; shared.jit.kernel: one
process compiles a cached kernel while the others wait for it."""

from __future__ import annotations

import fcntl
import os
import threading

import numpy as np
import pytest

from shared.jit import AVAILABLE, kernel, numba, one_signature

pytestmark = pytest.mark.skipif(not AVAILABLE, reason="needs numba")


def _corner_sum(a, ids):  # the same result for any layout
    return a[0, 0] + a[-1, -1] + ids[0]


def test_strided_and_contiguous_arrays_share_one_signature():
    kernel = one_signature(numba.njit(_corner_sum))
    grid = np.arange(24, dtype=np.float32).reshape(4, 6)
    ids = np.array([5, 6], np.int32)
    for a, expected in ((grid[:, ::2], 0 + 22 + 5), (grid, 0 + 23 + 5), (grid.T, 0 + 23 + 5)):
        assert kernel(a, ids) == expected
    assert len(kernel.signatures) == 1
    assert kernel.signatures[0][0].layout == "A"


def test_another_dtype_is_refused_not_compiled_again():
    kernel = one_signature(numba.njit(_corner_sum))
    kernel(np.zeros((2, 2), np.float32), np.zeros(1, np.int32))
    with pytest.raises(TypeError):
        kernel(np.zeros((2, 2), np.float32), np.zeros(1, np.int64))
    assert len(kernel.signatures) == 1


def test_an_argument_declared_read_only_takes_writable_and_read_only_arrays_in_either_order():
    ro = np.zeros((2, 2), np.float32)
    ro.flags.writeable = False
    ids = np.zeros(1, np.int32)
    for first, then in ((np.ones((2, 2), np.float32), ro), (ro, np.ones((2, 2), np.float32))):
        kernel = one_signature(numba.njit(_corner_sum), read_only=(0,))
        assert kernel(first, ids) == first[0, 0] + first[-1, -1]
        assert kernel(then, ids) == then[0, 0] + then[-1, -1]
        assert len(kernel.signatures) == 1 and not kernel.signatures[0][0].mutable
    # Without it, a read-only array after a writable first call is refused, not compiled again.
    kernel = one_signature(numba.njit(_corner_sum))
    kernel(np.ones((2, 2), np.float32), ids)
    with pytest.raises(TypeError):
        kernel(ro, ids)


def _plus_one(x):
    return x + 1


def test_a_cached_kernel_waits_for_the_process_that_holds_its_compile_lock():
    plus_one = kernel()(_plus_one)
    result = []
    os.makedirs(os.path.dirname(plus_one.cache_lock_path), exist_ok=True)
    fd = os.open(plus_one.cache_lock_path, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # another process compiling it (a lock of another open file, as theirs is)
        caller = threading.Thread(target=lambda: result.append(plus_one(np.int64(1))))
        caller.start()
        caller.join(0.5)
        assert caller.is_alive() and not result  # neither loaded from the cache nor compiled while it waits
    finally:
        os.close(fd)
    caller.join(60)
    assert result == [2]
