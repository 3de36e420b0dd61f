"""A real zenoh router with the generated ACL: each service may publish, serve and declare liveliness
only on its own key expressions (clients authenticated by user/password, one user per service)."""

from __future__ import annotations

import threading

import pytest

from deploy.zenoh import acl
from shared import keys
from shared.bus.base import QueryTarget
from tests.contract.conftest import Inbox, authenticated_router, wait_until

pytestmark = pytest.mark.contract

PASSWORDS = {svc: f"pw-{svc}-{i}" for i, svc in enumerate(acl.SERVICES)}


@pytest.fixture(scope="module")
def acl_net(tmp_path_factory):
    with authenticated_router(tmp_path_factory.mktemp("acl"), PASSWORDS) as router:
        clients = {svc: router.connect(svc) for svc in ("robot_io", "mapper", "renderer", "gateway", "planner",
                                                         "reconstructor")}
        yield clients, router.connect
        for c in clients.values():
            c.close()


def test_a_service_publishes_on_its_own_keys_only(acl_net):
    clients, _ = acl_net
    # The gateway reads both job event streams (it consumes them): the planner's and the mapper's.
    robot, mapper, gw = clients["planner"], clients["mapper"], clients["gateway"]
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on(k, data):
        with lock:
            got.append((k, data))

    pose = keys.MISSION_EVENTS.format(robot="robot0", mission="m1")
    graph = keys.EXPLORATION_EVENTS.format(robot="robot0", exploration="e1")
    subs = [gw.subscribe(keys.MISSION_EVENTS.pattern(), on), gw.subscribe(keys.EXPLORATION_EVENTS.pattern(), on)]
    # readiness: the subscriptions have reached the router once each owner's own sample gets through
    wait_until(lambda: robot.publish(pose, b"ready") or any(k == pose for k, _ in got), what="subscription routed")
    wait_until(lambda: mapper.publish(graph, b"ready") or any(k == graph for k, _ in got), what="subscription routed")
    # Each session's forbidden sample goes first, then an allowed one: once the allowed one arrived,
    # the forbidden one (same session, same router, in order) would have arrived too.
    robot.publish(graph, b"forged-graph")
    robot.publish(pose, b"pose-marker")
    mapper.publish(pose, b"forged-pose")
    mapper.publish(graph, b"graph-marker")
    wait_until(lambda: (pose, b"pose-marker") in got and (graph, b"graph-marker") in got, what="allowed samples")
    for sub in subs:
        sub.close()
    assert (graph, b"forged-graph") not in got
    assert (pose, b"forged-pose") not in got


def test_a_service_serves_its_own_queryables_only(acl_net):
    clients, _ = acl_net
    robot, renderer, gw = clients["robot_io"], clients["renderer"], clients["planner"]  # views' consumer
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


def test_a_service_subscribes_only_to_what_it_consumes(acl_net):
    """The renderer consumes map announcements, not the robot's frames: its subscription to the frames is
    refused by the router, while the reconstructor (their consumer) gets them."""
    clients, _ = acl_net
    robot, renderer, rec = clients["robot_io"], clients["renderer"], clients["reconstructor"]
    frame = keys.IO_FRAMES.format(robot="robot0", recording="t1")
    updated = keys.MAP_UPDATED.format(map="m1")
    at_renderer, at_rec = Inbox(), Inbox()
    forbidden = renderer.subscribe(keys.IO_FRAMES.pattern(), at_renderer)  # declared first ...
    allowed = renderer.subscribe(keys.MAP_UPDATED.pattern(), at_renderer)  # ... then this, same session
    sub_rec = rec.subscribe(keys.IO_FRAMES.pattern(), at_rec)
    wait_until(lambda: rec.publish(updated, b"ready") or at_renderer.has(updated), what="renderer's allowed sub")
    wait_until(lambda: robot.publish(frame, b"frame") or at_rec.has(frame, b"frame"), what="frames reach their consumer")
    # The router forwarded the frame to every admitted subscriber before the reconstructor saw it; a
    # sample the reconstructor publishes now reaches the renderer after it (same router, one session each).
    rec.publish(updated, b"after-frame")
    wait_until(lambda: at_renderer.has(updated, b"after-frame"), what="the marker after the frame")
    assert not at_renderer.has(frame), "the renderer read frames it does not consume"
    for c in (forbidden, allowed, sub_rec):
        c.close()


def test_a_service_queries_only_what_it_consumes(acl_net):
    """The planner may ask the robot for views (it consumes IO_VIEWS); the renderer may not."""
    clients, _ = acl_net
    robot, renderer, planner = clients["robot_io"], clients["renderer"], clients["planner"]
    views = keys.IO_VIEWS.format(robot="robot0")
    served = robot.serve([views], lambda k, p: b"views")

    def answers(bus):
        return [r.payload for r in bus.query(views, b"?", timeout_s=1.0, target=QueryTarget.ALL) if r.ok]

    wait_until(lambda: b"views" in answers(planner), what="robot-io's queryable routed to its consumer")
    assert answers(renderer) == []
    served.close()


@pytest.mark.parametrize("service", acl.SERVICES)
def test_no_service_may_read_everything(service):
    """No service's read rules hold ``ant/**`` or a key it neither owns nor consumes."""
    conf = acl.acl_config()
    rule = next(r for r in conf["rules"] if r["id"] == f"read-{service}")
    assert f"{keys.ROOT}/**" not in rule["key_exprs"]
    allowed = set(acl.consumed_key_exprs(service)) | set(acl.owned_key_exprs(service, acl.REPLICATED.get(service, ())))
    assert set(rule["key_exprs"]) == allowed
