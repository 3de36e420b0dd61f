"""Access control for the zenoh router, derived from :data:`shared.keys.CATALOGUE`.

Each service authenticates to the router with its own user name (zenoh ``usrpwd``); the router's
``access_control`` then lets it

* put / delete / declare queryables / reply / declare liveliness tokens **only on the key
  expressions it owns** (``Key.owner``), plus its own ``ant/alive/<service>/*`` token and its
  ``ant/svc/<service>/*/{info,metrics}`` queryables;
* subscribe, query and ask liveliness **only on the key expressions it consumes** (``Key.consumers``)
  or owns (least privilege: the renderer cannot subscribe to the robot's frames, the gateway cannot
  query the robot's motion keys);

* be handed (egress) samples, replies, tokens, subscriptions and queries **only on that same set** -
  what it owns or consumes, and its own ``alive``/``svc`` keys. Ingress alone would let a wildcard
  declaration that merely *intersects* a consumed key (``ant/**``) receive everything under it; egress
  drops every delivery outside the set. Read-only users (``readers``: the operator, tools) are still
  handed everything under ``ant/**``.

The robot's ROS 2 side (the stand-in, or a real robot's zenoh-bridge-ros2dds / rmw_zenoh router) joins
as its own user (:class:`Ros2Side`, ``ros2_robot``): it and the services that talk ROS 2 (robot-io) may
do everything on the ROS 2 key space of the configured key styles - the keys of the ROS names the robot
profiles use (``bridge``: the name itself, under the bridge's prefix or namespace; ``rmw_zenoh``:
``<domain>/<name>/<type>/<hash>`` and the domain's ``@ros2_lv`` graph tokens) - and nothing under
``ant/**``.

Replicated services (the renderer) also serve instance routes ``<key>/@<instance>``. A verbatim
``@`` chunk is matched by no wildcard, so those routes must be listed one by one: pass the instance
names the deployment gives its replicas (``ANT_INSTANCE``).

    python -m deploy.zenoh.acl --instances renderer=renderer-0,renderer-1 > deploy/zenoh/router-acl.json5
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from libs.ros2.action import action_names
from libs.ros2.keys import LIVELINESS_PREFIX, BridgeKeys, KeyStyleName, fully_qualified
from libs.ros2.profiles import PROFILES, STANDIN_OVERRIDES, Ros2Profile, profile
from shared import keys

SERVICES = ("robot_io", "mapper", "reconstructor", "renderer", "planner", "gateway")
# Services that serve instance routes (shared.runner Node.serve(..., replicated=True)).
REPLICATED = {"renderer": ("renderer-0", "renderer-1")}

# What an owner may originate on its own keys (router ingress from that client).
OWN_MESSAGES = ["put", "delete", "declare_queryable", "reply", "liveliness_token"]
# What a service may originate on the keys it consumes (and its own): ask, subscribe, watch tokens.
READ_MESSAGES = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
# What the router may hand a client: samples, replies and declarations (already checked on ingress).
DELIVER_MESSAGES = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]
# Egress: everything the router may hand a client, on the keys that client may see.
EGRESS_MESSAGES = list(dict.fromkeys([*DELIVER_MESSAGES, *READ_MESSAGES]))
# On the ROS 2 key space its parties do everything: publish, subscribe, serve, call, hold graph tokens.
ROS2_MESSAGES = list(dict.fromkeys([*OWN_MESSAGES, *READ_MESSAGES, *DELIVER_MESSAGES]))

# The Ros2Profile fields that name a ROS topic or service (the rest are frames, encodings, limits).
ROS_NAME_FIELDS = ("cmd_vel", "odom", "color", "camera_info", "depth", "semantic", "scan", "imu", "map", "tf",
                   "clock", "run_stop", "nav_mode_service", "teleport_service")


# The Ros2Profile fields that name a ROS action: its three services and two topics (libs.ros2.action).
ACTION_NAME_FIELDS = ("navigate_action", "spin_action")


def ros_names(prof: Ros2Profile) -> list[str]:
    """Every ROS topic and service name a profile uses (an action's as its services and topics)."""
    names = [v for f in ROS_NAME_FIELDS if (v := getattr(prof, f))]
    return names + [n for f in ACTION_NAME_FIELDS if (a := getattr(prof, f)) for n in action_names(a).values()]


def default_ros_names() -> tuple[str, ...]:
    """The names of every built-in profile and of the stand-in (its simulated clock, teleport, map)."""
    profs = [*PROFILES.values(), profile("generic", STANDIN_OVERRIDES)]
    return tuple(dict.fromkeys(n for p in profs for n in ros_names(p)))


@dataclass(frozen=True)
class Ros2Side:
    """The robot's ROS 2 zenoh network as the ACL sees it: its user, the key styles it may speak, the
    ROS names (``names``) and how they become keys (domain, namespace, the bridge's prefix)."""

    user: str = "ros2_robot"
    styles: tuple[str, ...] = (KeyStyleName.BRIDGE, KeyStyleName.RMW_ZENOH)
    names: tuple[str, ...] = field(default_factory=default_ros_names)
    domain_id: int = 0
    namespace: str = ""
    prefix: str = ""
    peers: tuple[str, ...] = ("robot_io",)  # the services that speak ROS 2


def _bridge_exprs(side: Ros2Side, name: str) -> list[str]:
    return [BridgeKeys(prefix=side.prefix, namespace=side.namespace).topic_key(name, None)]  # type: ignore[arg-type]


def _rmw_zenoh_exprs(side: Ros2Side, name: str) -> list[str]:
    # <domain>/<fq name>/<DDS type>/<RIHS01 hash>: the type and hash are one chunk each.
    return [f"{side.domain_id}/{fully_qualified(name, side.namespace).lstrip('/')}/*/*"]


# Key style -> (the key expressions of one ROS name, the style's graph key expressions).
ROS2_KEY_STYLES: dict[str, tuple[Callable[[Ros2Side, str], list[str]], Callable[[Ros2Side], list[str]]]] = {
    KeyStyleName.BRIDGE: (_bridge_exprs, lambda side: []),  # the bridge discovers DDS itself: no tokens
    KeyStyleName.RMW_ZENOH: (_rmw_zenoh_exprs, lambda side: [f"{LIVELINESS_PREFIX}/{side.domain_id}/**"]),
}


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


def consumed_key_exprs(service: str, instances: Mapping[str, Sequence[str]] | None = None) -> list[str]:
    """Every key expression ``service`` may subscribe to, query or watch tokens on: the keys whose
    ``Key.consumers`` name it, their advanced-publisher caches (``@adv``, history and late joiners)
    and, for a replicated owner, its instance routes (a balancing client addresses one replica)."""
    if service not in SERVICES:
        raise AclError(f"unknown service {service!r}; known: {', '.join(SERVICES)}")
    instances = REPLICATED if instances is None else instances
    consumed = [k for k in keys.CATALOGUE if service in k.consumers]
    out = [_expr(k) for k in consumed]
    out += [f"{_expr(k)}/@adv/**" for k in consumed if k.usage == keys.Usage.PUBLICATION]
    for k in consumed:
        if k.usage == keys.Usage.QUERYABLE:
            out += [keys.routed(_expr(k), inst) for inst in instances.get(k.owner, ())]
    return list(dict.fromkeys(out))


def routed_key_exprs(instances: Mapping[str, Sequence[str]]) -> list[str]:
    """Every instance route of every replicated service (verbatim chunks need explicit listing)."""
    return [e for svc, names in instances.items() for e in owned_key_exprs(svc, names)
            if "/@" in e]


def ros2_key_exprs(side: Ros2Side) -> list[str]:
    """The ROS 2 key space of ``side``: every name in every key style, and the styles' graph tokens.
    Refuses a name whose key would fall under ``ant/**`` (the ROS side must never forge a service)."""
    if not 0 <= side.domain_id <= 232:  # ROS_DOMAIN_ID's range
        raise AclError(f"ROS domain id out of range 0..232: {side.domain_id}")
    out: list[str] = []
    for style in side.styles:
        try:
            per_name, graph = ROS2_KEY_STYLES[style]
        except KeyError:
            raise AclError(f"unknown ROS 2 key style {style!r}; known: {', '.join(ROS2_KEY_STYLES)}") from None
        out += [e for n in side.names for e in per_name(side, n)] + graph(side)
    for e in out:
        if e == keys.ROOT or e.startswith(f"{keys.ROOT}/") or e.split("/", 1)[0] in ("*", "**"):
            raise AclError(f"the ROS 2 key {e!r} would overlap the services' {keys.ROOT}/**")
    return list(dict.fromkeys(out))


def acl_config(services: Iterable[str] = SERVICES,
               instances: Mapping[str, Sequence[str]] | None = None,
               default_permission: str = "deny", readers: Sequence[str] = (),
               ros2: Ros2Side | None = None) -> dict[str, Any]:
    """The router's ``access_control`` section (zenoh 1.x: rules, subjects, policies).

    Subjects match the ``usrpwd`` user name, which must equal the service name. ``readers`` are extra
    users (tools, tests) that may read and query everything but publish, serve or declare nothing.
    ``ros2``: the robot's ROS 2 side, its own subject, sharing its key space with ``ros2.peers`` only.
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
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    if readers:  # the operator, tools and tests: read, query and be handed everything, originate nothing
        rules.append({"id": "read-all", "permission": "allow", "flows": ["ingress"], "messages": READ_MESSAGES,
                      "key_exprs": everywhere})
        rules.append({"id": "deliver-all", "permission": "allow", "flows": ["egress"], "messages": EGRESS_MESSAGES,
                      "key_exprs": everywhere})
        subjects += [{"id": r, "usernames": [r]} for r in readers]
        policies.append({"id": "readers", "rules": ["read-all", "deliver-all"], "subjects": list(readers)})
    for svc in services:
        owned = owned_key_exprs(svc, instances.get(svc, ()))
        rules.append({"id": f"own-{svc}", "permission": "allow", "flows": ["ingress"], "messages": OWN_MESSAGES,
                      "key_exprs": owned})
        # A service reads what it consumes, and its own keys (an owner may look at what it serves).
        readable = list(dict.fromkeys([*consumed_key_exprs(svc, instances), *owned]))
        rules.append({"id": f"read-{svc}", "permission": "allow", "flows": ["ingress"], "messages": READ_MESSAGES,
                      "key_exprs": readable})
        # Egress mirrors ingress: the router hands a service only what it owns or consumes - samples,
        # replies and tokens of the keys it reads, and the subscriptions, queries and token watches of
        # its consumers on the keys it owns. A declaration that slips through ingress (a wildcard that
        # merely intersects a consumed key) still delivers nothing outside that set.
        # The gateway asks every instance at once (``ant/svc/*/*/info``, ``.../metrics``): the router
        # hands that query on under its wildcard key, which no one service's own info key includes, so
        # every service is also handed the all-services form (ingress still lets only the gateway ask).
        everyone = [keys.INFO.pattern(), keys.METRICS.pattern()]
        rules.append({"id": f"deliver-{svc}", "permission": "allow", "flows": ["egress"],
                      "messages": EGRESS_MESSAGES, "key_exprs": list(dict.fromkeys([*readable, *everyone]))})
        subjects.append({"id": svc, "usernames": [svc]})
        policies.append({"id": f"{svc}-owns", "rules": [f"own-{svc}", f"read-{svc}", f"deliver-{svc}"],
                         "subjects": [svc]})
    if ros2 is not None:
        peers = [p for p in ros2.peers if p in services]
        rules.append({"id": "ros2", "permission": "allow", "flows": ["ingress", "egress"], "messages": ROS2_MESSAGES,
                      "key_exprs": ros2_key_exprs(ros2)})
        subjects.append({"id": ros2.user, "usernames": [ros2.user]})
        policies.append({"id": "ros2-side", "rules": ["ros2"], "subjects": [ros2.user, *peers]})
    return {"enabled": True, "default_permission": default_permission, "rules": rules, "subjects": subjects,
            "policies": policies}


def router_config(listen: Sequence[str] = ("tcp/[::]:7447",), *, users_file: str = "/etc/zenoh/users.txt",
                  services: Iterable[str] = SERVICES, instances: Mapping[str, Sequence[str]] | None = None,
                  readers: Sequence[str] = (), ros2: Ros2Side | None = None) -> dict[str, Any]:
    """A complete router configuration with user/password authentication and the ACL."""
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": users_file}}},
        "access_control": acl_config(services, instances, readers=readers, ros2=ros2),
    }


def client_config(service: str, password: str, connect: Sequence[str] = ("tcp/router:7447",)) -> dict[str, Any]:
    """A service's (or the ROS 2 side's) client config: client mode (all traffic through the ACL router)
    with its credentials."""
    if service not in (*SERVICES, Ros2Side.user):
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
access control: each service may publish, serve and declare liveliness only on its own key expressions,
and subscribe, query and watch liveliness only on the keys it consumes (Key.consumers) or owns.
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
