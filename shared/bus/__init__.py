"""The bus port and its adapters. Import :mod:`shared.bus.zenoh_bus` only in entry points."""

from shared.bus.base import Bus, Closeable, QueryFailed, QueryTarget, Reply
from shared.bus.fake import FakeBus, FakeNetwork

__all__ = ["Bus", "Closeable", "FakeBus", "FakeNetwork", "QueryFailed", "QueryTarget", "Reply"]
