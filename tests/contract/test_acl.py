"""A real zenoh router with the generated ACL: each service may publish, serve and declare liveliness
only on its own key expressions (clients authenticated by user/password, one user per service)."""

from __future__ import annotations

import threading

import pytest

from deploy.zenoh import acl
from shared import keys
from shared.bus.base import QueryTarget
from tests.contract.conftest import authenticated_router, wait_until

pytestmark = pytest.mark.contract

PASSWORDS = {svc: f"pw-{svc}-{i}" for i, svc in enumerate(acl.SERVICES)}


@pytest.fixture(scope="module")
def acl_net(tmp_path_factory):
    with authenticated_router(tmp_path_factory.mktemp("acl"), PASSWORDS) as router:
        clients = {svc: router.connect(svc) for svc in ("robot_io", "mapper", "renderer", "gateway")}
        yield clients, router.connect
        for c in clients.values():
            c.close()


def test_a_service_publishes_on_its_own_keys_only(acl_net):
    clients, _ = acl_net
    robot, mapper, gw = clients["robot_io"], clients["mapper"], clients["gateway"]
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on(k, data):
        with lock:
            got.append((k, data))

    sub = gw.subscribe("ant/**", on)
    pose = keys.IO_POSE.format(robot="robot0")
    graph = keys.MAPPER_GRAPH.format(robot="robot0")
    # readiness: the subscription has reached the router once robot-io's own pose gets through
    wait_until(lambda: robot.publish(pose, b"ready") or any(k == pose for k, _ in got), what="subscription routed")
    # Each session's forbidden sample goes first, then an allowed one: once the allowed one arrived,
    # the forbidden one (same session, same router, in order) would have arrived too.
    robot.publish(graph, b"forged-graph")
    robot.publish(pose, b"pose-marker")
    mapper.publish(pose, b"forged-pose")
    mapper.publish(graph, b"graph-marker")
    wait_until(lambda: (pose, b"pose-marker") in got and (graph, b"graph-marker") in got, what="allowed samples")
    sub.close()
    assert (graph, b"forged-graph") not in got
    assert (pose, b"forged-pose") not in got


def test_a_service_serves_its_own_queryables_only(acl_net):
    clients, _ = acl_net
    robot, renderer, gw = clients["robot_io"], clients["renderer"], clients["gateway"]
    views = keys.RENDER_VIEWS.format()
    route = keys.routed(views, "renderer-0")  # named in the generated ACL's default replicas
    hijack = robot.serve([views, route], lambda k, p: b"hijacked")
    real = renderer.serve([views, route], lambda k, p: b"rendered")

    def answers(key):
        return [r.payload for r in gw.query(key, b"?", timeout_s=1.0, target=QueryTarget.ALL) if r.ok]

    wait_until(lambda: b"rendered" in answers(views), what="renderer's queryable routed")
    wait_until(lambda: b"rendered" in answers(route), what="renderer's instance route")
    assert b"hijacked" not in answers(views) + answers(route)
    hijack.close()
    real.close()


def test_liveliness_of_another_service_cannot_be_forged(acl_net):
    clients, _ = acl_net
    robot, renderer, gw = clients["robot_io"], clients["renderer"], clients["gateway"]
    fake = robot.liveliness_token(keys.ALIVE.format(service="renderer", instance="impostor"))
    real = renderer.liveliness_token(keys.ALIVE.format(service="renderer", instance="genuine"))
    seen = wait_until(lambda: gw.alive(keys.ALIVE.pattern(service="renderer"), timeout_s=1.0), what="token seen")
    assert keys.ALIVE.format(service="renderer", instance="genuine") in seen
    assert all(not t.endswith("/impostor") for t in gw.alive(keys.ALIVE.pattern(), timeout_s=1.0))
    fake.close()
    real.close()


def test_a_wrong_password_is_refused(acl_net):
    _, connect = acl_net
    with pytest.raises(Exception, match="(?i)unable to connect"):
        connect("renderer", "not-the-password")
