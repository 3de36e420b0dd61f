"""Transient-local (latched) topics as rmw_zenoh does them (issue 34, item 1): a map_server
publishes /map once; a subscriber that joins later gets it on joining, from the publisher's cache,
over real zenoh sessions, in both key styles. Without the cache a late joiner waits forever (the
map is never published again), so each test also checks a volatile publisher's sample does not
reach the late joiner: the test can fail."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from deploy.launcher import free_port
from libs.ros2 import messages as msgs
from libs.ros2.keys import Qos, key_style
from libs.ros2.node import Ros2Node
from services.robot_io.ros2_zenoh import ZenohRos2Transport, ZenohTransportConfig
from shared.bus.config import ZenohSettings
from tests.waiting import wait_until

pytestmark = pytest.mark.contract

LATCHED = Qos(transient_local=True, depth=1)


def transport(*, listen=(), connect=()):
    return ZenohRos2Transport(ZenohTransportConfig(zenoh=ZenohSettings(listen=list(listen), connect=list(connect))))


def grid(value: int) -> np.ndarray:
    g = np.zeros((20, 30), np.int8)
    g[5, :] = value
    return g


@pytest.mark.parametrize("keys", ["bridge", "rmw_zenoh"])
def test_a_map_published_once_reaches_a_subscriber_that_joins_later(keys):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server_t = transport(listen=[endpoint])
    server = Ros2Node(server_t, key_style(keys), "map_server")
    pub = server.publisher("/map", msgs.MESSAGES["occupancy_grid"], LATCHED)
    # Two publications: the cache keeps the last one (depth 1), which is what a late joiner gets.
    pub.publish(msgs.occupancy_grid(1.0, "map", grid(50), 0.05, (-1.0, -2.0)))
    pub.publish(msgs.occupancy_grid(2.0, "map", grid(100), 0.05, (-1.0, -2.0)))
    volatile = server.publisher("/map_updates", msgs.MESSAGES["occupancy_grid"], Qos())
    volatile.publish(msgs.occupancy_grid(3.0, "map", grid(100), 0.05, (-1.0, -2.0)))

    # The backend starts after both were published, in its own session.
    late_t = transport(connect=[endpoint])
    late = Ros2Node(late_t, key_style(keys), "backend")
    got, updates = [], []
    arrived = threading.Event()
    late.subscribe("/map", msgs.MESSAGES["occupancy_grid"], lambda msg, _r: (got.append(msg), arrived.set()), LATCHED)
    late.subscribe("/map_updates", msgs.MESSAGES["occupancy_grid"], lambda msg, _r: updates.append(msg), Qos())
    try:
        # Bounded wait: the history query's round trip on loopback; nothing is ever re-published.
        wait_until(arrived.is_set, 20, "the latched /map at the late subscriber")
        # A later publication still arrives as a live sample.
        pub.publish(msgs.occupancy_grid(4.0, "map", grid(7), 0.05, (-1.0, -2.0)))
        wait_until(lambda: len(got) >= 2, 20, "the live /map after the latched one")
    finally:
        late.close(); late_t.close(); server.close(); server_t.close()
    first = got[0]
    assert (first.info.width, first.info.height) == (30, 20)
    assert first.header.stamp.sec == 2  # the last sample kept, not the first
    assert int(np.asarray(first.data, np.int8).reshape(20, 30)[5, 0]) == 100
    assert got[1].header.stamp.sec == 4
    assert updates == []  # volatile: a late joiner never sees what was published before it joined
