"""The ACL example is derived from shared.keys and covers every key of the catalogue."""

from __future__ import annotations

import json

import pytest
import zenoh

from deploy.zenoh import acl
from shared import keys
from tests.conftest import REPO_ROOT

ZENOH_DIR = REPO_ROOT / "deploy" / "zenoh"


def includes(outer: str, inner: str) -> bool:
    return zenoh.KeyExpr(outer).includes(zenoh.KeyExpr(inner))


def covered(exprs: list[str], key: str) -> bool:
    return any(includes(e, key) for e in exprs)


def test_every_owned_key_is_covered_by_its_owner_and_no_one_else():
    owned = {svc: acl.owned_key_exprs(svc) for svc in acl.SERVICES}
    for key in keys.CATALOGUE:
        concrete = key.pattern()
        if key.owner == "*":
            for svc in acl.SERVICES:
                mine = key.pattern(service=svc)
                assert covered(owned[svc], mine), f"{svc} cannot use its own {key.template}"
                others = [o for o in acl.SERVICES if o != svc]
                assert not any(covered(owned[o], mine) for o in others), f"another service covers {mine}"
            continue
        assert key.owner in acl.SERVICES, f"{key.template}: unknown owner {key.owner!r}"
        assert covered(owned[key.owner], concrete), f"{key.template} is not in {key.owner}'s ACL rule"
        for other in acl.SERVICES:
            if other != key.owner:
                assert not covered(owned[other], concrete), f"{other} may publish/serve {key.template}"


def test_instance_routes_are_listed_for_named_replicas_only():
    exprs = acl.owned_key_exprs("renderer", ["r-a", "r-b"])
    view = keys.routed(keys.RENDER_VIEWS.format(), "r-a")
    assert view in exprs and keys.routed(keys.RENDER_MAP.format(), "r-b") in exprs
    # a verbatim @chunk is matched by no wildcard: an unnamed replica would not be covered
    assert not covered([e for e in exprs if "@" not in e], view)
    assert not covered(exprs, keys.routed(keys.RENDER_VIEWS.format(), "r-c"))
    conf = acl.acl_config(instances={"renderer": ["r-a"]})
    # the consumer of the views (the planner) may address a replica; a non-consumer (the gateway) may not
    read = next(r for r in conf["rules"] if r["id"] == "read-planner")
    assert view in read["key_exprs"]
    assert view not in next(r for r in conf["rules"] if r["id"] == "read-gateway")["key_exprs"]


def test_acl_shape_is_what_zenoh_accepts(tmp_path):
    conf = acl.router_config(["tcp/127.0.0.1:7447"], users_file=str(tmp_path / "users.txt"))
    ids = [r["id"] for r in conf["access_control"]["rules"]]
    assert len(ids) == len(set(ids))
    subjects = {s["id"] for s in conf["access_control"]["subjects"]}
    for p in conf["access_control"]["policies"]:
        assert set(p["rules"]) <= set(ids) and set(p["subjects"]) <= subjects
    path = tmp_path / "router.json5"
    path.write_text(acl.render(conf, "header"))
    parsed = json.loads(zenoh.Config.from_file(str(path)).get_json("access_control"))
    assert parsed["default_permission"] == "deny" and parsed["enabled"] is True


def test_checked_in_example_is_up_to_date():
    text = (ZENOH_DIR / "router-acl.json5").read_text()
    assert text == acl.render(acl.router_config(), acl.HEADER), (
        "deploy/zenoh/router-acl.json5 is stale: python -m deploy.zenoh.acl > deploy/zenoh/router-acl.json5")


def test_bad_input_is_refused():
    with pytest.raises(acl.AclError):
        acl.owned_key_exprs("teleporter")
    with pytest.raises(acl.AclError):
        acl.parse_instances(["renderer"])
    with pytest.raises(keys.KeyExprError):
        acl.parse_instances(["renderer=a/b"])
    with pytest.raises(acl.AclError):
        acl.acl_config(services=["mapper"], instances={"renderer": ["r0"]})
    assert acl.parse_instances(["renderer=r0, r1"]) == {"renderer": ["r0", "r1"]}


@pytest.mark.parametrize("name", ["router.json5", "router-acl.json5", "client-acl.example.json5",
                                  "tls/router.json5", "tls/client.json5"])
def test_example_configs_parse_in_zenoh(name):
    # zenoh refuses unknown keys, so this catches a misspelt or outdated option
    conf = zenoh.Config.from_file(str(ZENOH_DIR / name))
    assert json.loads(conf.get_json("mode")) in ("router", "client", "peer")


def test_users_example_has_one_user_per_service():
    lines = (ZENOH_DIR / "users.example.txt").read_text().split()
    assert sorted(line.split(":", 1)[0] for line in lines) == sorted(acl.SERVICES)
