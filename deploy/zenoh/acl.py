"""Access control for the zenoh router, derived from :data:`shared.keys.CATALOGUE`.

Each service authenticates to the router with its own user name (zenoh ``usrpwd``); the router's
``access_control`` then lets it

* put / delete / declare queryables / reply / declare liveliness tokens **only on the key
  expressions it owns** (``Key.owner``), plus its own ``ant/alive/<service>/*`` token and its
  ``ant/svc/<service>/*/{info,metrics}`` queryables;
* subscribe and query anything under ``ant/**`` (every service reads others' topics);

and the router delivers every sample, reply and declaration under ``ant/**`` to everyone.

Replicated services (the renderer) also serve instance routes ``<key>/@<instance>``. A verbatim
``@`` chunk is matched by no wildcard, so those routes must be listed one by one: pass the instance
names the deployment gives its replicas (``ANT_INSTANCE``).

    python -m deploy.zenoh.acl --instances renderer=renderer-0,renderer-1 > deploy/zenoh/router-acl.json5
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from shared import keys

SERVICES = ("robot_io", "mapper", "reconstructor", "renderer", "planner", "gateway")
# Services that serve instance routes (shared.runner Node.serve(..., replicated=True)).
REPLICATED = {"renderer": ("renderer-0", "renderer-1")}

# What an owner may originate on its own keys (router ingress from that client).
OWN_MESSAGES = ["put", "delete", "declare_queryable", "reply", "liveliness_token"]
# What everyone may originate anywhere under the root (reading is not restricted).
READ_MESSAGES = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
# What the router may hand to any client: samples, replies and declarations (already checked on ingress).
DELIVER_MESSAGES = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]


class AclError(ValueError):
    """The requested ACL cannot be built (unknown service, bad instance name)."""


def _expr(key: keys.Key) -> str:
    """The key's template with every ``{part}`` as ``*`` (one chunk, as Key.format guarantees)."""
    return key.pattern()


def owned_key_exprs(service: str, instances: Sequence[str] = ()) -> list[str]:
    """Every key expression ``service`` may publish, serve or declare a token on."""
    if service not in SERVICES:
        raise AclError(f"unknown service {service!r}; known: {', '.join(SERVICES)}")
    out = [keys.ALIVE.pattern(service=service), keys.INFO.pattern(service=service),
           keys.METRICS.pattern(service=service)]
    owned = [k for k in keys.CATALOGUE if k.owner == service]
    out += [_expr(k) for k in owned]
    # zenoh-ext's advanced publishers (the event caches late subscribers recover from) declare their
    # token and cache queryable under the verbatim chunk ``@adv`` below the key: list it explicitly.
    out += [f"{_expr(k)}/@adv/**" for k in owned if k.usage == keys.Usage.PUBLICATION]
    for inst in instances:
        out += [keys.routed(_expr(k), inst) for k in owned if k.usage == keys.Usage.QUERYABLE]
    return list(dict.fromkeys(out))


def routed_key_exprs(instances: Mapping[str, Sequence[str]]) -> list[str]:
    """Every instance route of every replicated service (verbatim chunks need explicit listing)."""
    return [e for svc, names in instances.items() for e in owned_key_exprs(svc, names)
            if "/@" in e]


def acl_config(services: Iterable[str] = SERVICES,
               instances: Mapping[str, Sequence[str]] | None = None,
               default_permission: str = "deny", readers: Sequence[str] = ()) -> dict[str, Any]:
    """The router's ``access_control`` section (zenoh 1.x: rules, subjects, policies).

    Subjects match the ``usrpwd`` user name, which must equal the service name. ``readers`` are extra
    users (tools, tests) that may read and query everything but publish, serve or declare nothing.
    """
    services = list(services)
    instances = dict(REPLICATED if instances is None else instances)
    for svc, names in instances.items():
        if svc not in services:
            raise AclError(f"instances given for {svc!r}, which is not among {services}")
        for n in names:
            keys.validate_segment(n, "instance")
    # "@adv": advanced subscribers' tokens and history queries (a verbatim chunk no wildcard matches).
    everywhere = [f"{keys.ROOT}/**", f"{keys.ROOT}/**/@adv/**", *routed_key_exprs(instances)]
    rules: list[dict[str, Any]] = [
        {"id": "read", "permission": "allow", "flows": ["ingress", "egress"], "messages": READ_MESSAGES,
         "key_exprs": everywhere},
        {"id": "deliver", "permission": "allow", "flows": ["egress"], "messages": DELIVER_MESSAGES,
         "key_exprs": everywhere},
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = [{"id": "everyone", "rules": ["read", "deliver"],
                                       "subjects": [*services, *readers]}]
    subjects += [{"id": r, "usernames": [r]} for r in readers]
    for svc in services:
        rules.append({"id": f"own-{svc}", "permission": "allow", "flows": ["ingress"], "messages": OWN_MESSAGES,
                      "key_exprs": owned_key_exprs(svc, instances.get(svc, ()))})
        subjects.append({"id": svc, "usernames": [svc]})
        policies.append({"id": f"{svc}-owns", "rules": [f"own-{svc}"], "subjects": [svc]})
    return {"enabled": True, "default_permission": default_permission, "rules": rules, "subjects": subjects,
            "policies": policies}


def router_config(listen: Sequence[str] = ("tcp/[::]:7447",), *, users_file: str = "/etc/zenoh/users.txt",
                  services: Iterable[str] = SERVICES, instances: Mapping[str, Sequence[str]] | None = None,
                  readers: Sequence[str] = ()) -> dict[str, Any]:
    """A complete router configuration with user/password authentication and the ACL."""
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": users_file}}},
        "access_control": acl_config(services, instances, readers=readers),
    }


def client_config(service: str, password: str, connect: Sequence[str] = ("tcp/router:7447",)) -> dict[str, Any]:
    """A service's side: client mode (all traffic through the ACL router) with its credentials."""
    if service not in SERVICES:
        raise AclError(f"unknown service {service!r}")
    return {
        "mode": "client",
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": service, "password": password}}},
    }


def render(config: Mapping[str, Any], header: str = "") -> str:
    """JSON5 text (strict JSON is valid JSON5) with a comment header."""
    lines = [f"// {line}" if line else "//" for line in header.splitlines()]
    return "\n".join([*lines, json.dumps(config, indent=2)]) + "\n"


def parse_instances(specs: Sequence[str]) -> dict[str, list[str]]:
    """``["renderer=renderer-0,renderer-1"]`` -> ``{"renderer": ["renderer-0", "renderer-1"]}``."""
    out: dict[str, list[str]] = {}
    for spec in specs:
        svc, sep, names = spec.partition("=")
        if not sep or not names:
            raise AclError(f"--instances wants SERVICE=NAME[,NAME...], got {spec!r}")
        out[svc] = [keys.validate_segment(n.strip(), "instance") for n in names.split(",")]
    return out


HEADER = """\
Generated by `python -m deploy.zenoh.acl` from shared/keys.py - do not edit by hand
(tests/unit/deploy/test_acl_config.py fails when it is stale).
A zenoh router with user/password authentication (one user per service, see users.example.txt) and
access control: each service may publish, serve and declare liveliness only on its own key expressions.
Services connect in client mode with deploy/zenoh/client-acl.example.json5 (their user name = service name)."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Print the ACL router config derived from shared/keys.py")
    ap.add_argument("--instances", action="append", default=[],
                    help="replica names of a replicated service, e.g. renderer=renderer-0,renderer-1")
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--users-file", default="/etc/zenoh/users.txt")
    args = ap.parse_args(argv)
    instances = parse_instances(args.instances) if args.instances else None
    conf = router_config(args.listen or ["tcp/[::]:7447"], users_file=args.users_file, instances=instances)
    sys.stdout.write(render(conf, HEADER))
    return 0


if __name__ == "__main__":
    sys.exit(main())
