"""The router's egress follows the topology too (issue 31): a service is handed only what it owns or
consumes. Ingress already refuses any declaration that is not inside a service's own key set (a wildcard
that merely intersects a consumed key is refused whole: tried with ``ant/**``, ``ant/maps/**``), so
samples, replies and tokens could not reach a non-party before either. What egress adds is the
declarations: without it the router told every service who subscribes where - a publisher's matching
status on a key it neither owns nor consumes said whether the gateway listened there."""

from __future__ import annotations

import pytest

from deploy.zenoh import acl
from shared import keys
from tests.contract.conftest import Inbox, authenticated_router, wait_until

pytestmark = pytest.mark.contract

PASSWORDS = {svc: f"pw-{svc}-egress" for svc in acl.SERVICES}


def test_egress_hides_subscriptions_from_services_not_taking_part(tmp_path):
    """The mapper is told of the gateway's subscription to its exploration events (it owns them), not of
    the gateway's subscription to the planner's mission events (it neither owns nor consumes those)."""
    with authenticated_router(tmp_path, PASSWORDS) as router:
        gw, planner, mapper = (router.connect(s) for s in ("gateway", "planner", "mapper"))
        try:
            mission = keys.MISSION_EVENTS.format(robot="robot0", mission="m1")
            exploration = keys.EXPLORATION_EVENTS.format(robot="robot0", exploration="e1")
            # Declaring a publisher is not an ACL'd message: any client may hold one and read its
            # matching status, which is fed by the subscriber declarations the router hands it (egress).
            owner = planner.session.declare_publisher(mission)
            spy = mapper.session.declare_publisher(mission)
            mapper_own = mapper.session.declare_publisher(exploration)
            inbox = Inbox()
            subs = [gw.subscribe(keys.MISSION_EVENTS.pattern(), inbox),  # declared first ...
                    gw.subscribe(keys.EXPLORATION_EVENTS.pattern(), inbox)]  # ... then this, same session
            wait_until(lambda: owner.matching_status.matching, what="the owner told of its consumer")
            wait_until(lambda: mapper_own.matching_status.matching, what="the mapper told of its consumer")
            # The gateway's two declarations travel in order through one router: once the second reached
            # the mapper, the first would have too, had egress let it.
            assert not spy.matching_status.matching, "the mapper was told who subscribes to mission events"
            wait_until(lambda: planner.publish(mission, b"step") or inbox.has(mission, b"step"),
                       what="mission events still reach their consumer")
            for s in subs:
                s.close()
            for p in (owner, spy, mapper_own):
                p.undeclare()
        finally:
            for c in (gw, planner, mapper):
                c.close()


@pytest.mark.parametrize("service", acl.SERVICES)
def test_egress_of_a_service_is_what_it_owns_or_consumes(service):
    conf = acl.acl_config()
    rule = next(r for r in conf["rules"] if r["id"] == f"deliver-{service}")
    assert rule["flows"] == ["egress"]
    assert f"{keys.ROOT}/**" not in rule["key_exprs"]
    allowed = set(acl.consumed_key_exprs(service)) | set(acl.owned_key_exprs(service, acl.REPLICATED.get(service, ())))
    # ... and the gateway's all-instances info/metrics query, which reaches each service under its
    # wildcard key (without it /status saw no instance's details: tests/e2e/test_launch.py).
    allowed |= {keys.INFO.pattern(), keys.METRICS.pattern()}
    assert set(rule["key_exprs"]) == allowed
    # No rule hands a service everything any more; only read-only users get that.
    policies = [p for p in conf["policies"] if service in p["subjects"]]
    assert [p["id"] for p in policies] == [f"{service}-owns"]


def test_readers_are_still_handed_everything():
    conf = acl.acl_config(readers=["operator"])
    pol = next(p for p in conf["policies"] if p["subjects"] == ["operator"])
    deliver = next(r for r in conf["rules"] if r["id"] in pol["rules"] and r["flows"] == ["egress"])
    assert f"{keys.ROOT}/**" in deliver["key_exprs"]
