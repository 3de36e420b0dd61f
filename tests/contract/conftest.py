"""Two real zenoh peers in one process, on 127.0.0.1 with a free port and multicast off."""

from __future__ import annotations


from tests.waiting import wait_until

__all__ = ["wait_until"]  # the two-peer fixture ``peers`` lives in tests/conftest.py
