"""Zenoh access control for the swarm: who may put, subscribe and ask on which keys.

Theory of operation
-------------------
Over IP, Zenoh's mutual TLS tells a router (or a listening node) which certificate a
connected node holds; its access control (the ``access_control`` section of a Zenoh
config) then decides, per message and key, by the certificate's common name. The
swarm's certificates (:mod:`swarm.runtime.keyspace.pki`) name the node (CN) and its role
(OU): ``agent``, ``station`` or ``router``. :func:`acl` turns the list of nodes into
that section, default deny, with these rules ("in": what the node may send into the
router, "out": what the router passes on to it):

* an **agent** A puts only its own keys: ``swarm/advertize``, ``swarm/GSAdvertize``,
  ``swarm/A/pose``, ``swarm/A/state`` and the inboxes ``swarm/<name>`` (the election
  sends P2P messages to its peers' and answers stations there); never
  ``swarm/*/command`` nor anything under ``gcs/``. It subscribes to, and is given,
  its own inbox and command key, the advertisements and the pose streams, and
  nothing else (another agent's inbox, a station's state: not for it);
* a **station** S puts ``swarm/GSAdvertize``, the inboxes, the agents' command keys
  ``swarm/*/command`` (only stations command) and its own ``gcs/S/state``;
  subscribes to ``swarm/**`` and ``gcs/*/state``; answers queries on its own
  ``gcs/S/command`` and asks the other stations' ``gcs/*/command``;
* a **router** R passes everything (it carries other nodes' traffic; each router
  enforces these rules on the nodes connected to it).

A certificate not listed, or a node without one (plain TCP), matches no subject and
is denied everything. Names are the swarm's (1 to 16 letters, digits, ``_``, ``-``),
so a name is one key chunk. Pure: a list of nodes in, a dict out (JSON, which Zenoh
reads as JSON5).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from swarm.core.wire.message_types import NAME_RE

ROLES = ("agent", "station", "router")

ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
)


@dataclass(frozen=True)
class Node:
    """A certificate's holder: its name (the certificate's CN) and role (its OU)."""

    name: str
    role: str

    def __post_init__(self) -> None:
        if not NAME_RE.match(self.name):
            raise ValueError(f"node name {self.name!r}: 1 to 16 letters, digits, '_' or '-'")
        if self.role not in ROLES:
            raise ValueError(f"role {self.role!r}: one of {', '.join(ROLES)}")


def _rule(rid: str, messages: Sequence[str], flow: str, keys: Sequence[str]) -> dict[str, Any]:
    return {
        "id": rid,
        "messages": list(messages),
        "flows": [flow],
        "permission": "allow",
        "key_exprs": list(keys),
    }


def agent_rules(name: str) -> list[dict[str, Any]]:
    own = [f"swarm/{name}", f"swarm/{name}/command"]
    heard = ["swarm/advertize", "swarm/GSAdvertize", "swarm/*/pose"]
    return [
        _rule(
            f"agent-{name}-put",
            ["put"],
            "ingress",
            ["swarm/advertize", "swarm/GSAdvertize", "swarm/*", f"swarm/{name}/pose", f"swarm/{name}/state"],
        ),
        _rule(f"agent-{name}-subscribe", ["declare_subscriber"], "ingress", [*own, *heard]),
        _rule(f"agent-{name}-hear", ["put"], "egress", [*own, *heard]),
    ]


def station_rules(name: str) -> list[dict[str, Any]]:
    mine = f"gcs/{name}/command"
    return [
        _rule(
            f"station-{name}-put",
            ["put"],
            "ingress",
            ["swarm/GSAdvertize", "swarm/*", "swarm/*/command", f"gcs/{name}/state"],
        ),
        _rule(f"station-{name}-subscribe", ["declare_subscriber"], "ingress", ["swarm/**", "gcs/*/state"]),
        _rule(f"station-{name}-hear", ["put"], "egress", ["swarm/**", "gcs/*/state"]),
        _rule(f"station-{name}-ask", ["query"], "ingress", ["gcs/*/command"]),
        _rule(f"station-{name}-answers", ["reply"], "egress", ["gcs/*/command"]),
        _rule(f"station-{name}-serve", ["declare_queryable", "reply"], "ingress", [mine]),
        _rule(f"station-{name}-asked", ["query"], "egress", [mine]),
    ]


#: what every agent and station is told of: where the subscribers and queryables are
#: (a Zenoh node sends only where someone listens)
SHARED_RULES = [
    _rule("learn-subscribers", ["declare_subscriber"], "egress", ["swarm/**", "gcs/**"]),
    _rule("learn-queryables", ["declare_queryable"], "egress", ["gcs/*/command"]),
]
ROUTER_RULES = [
    _rule("router-in", ALL_MESSAGES, "ingress", ["**"]),
    _rule("router-out", ALL_MESSAGES, "egress", ["**"]),
]


def acl(nodes: Iterable[Node]) -> dict[str, Any]:
    """The ``access_control`` section for ``nodes`` (see the module docstring).

    Raises:
        ValueError: a name given twice.
    """
    rules: list[dict[str, Any]] = [*SHARED_RULES, *ROUTER_RULES]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    routers: list[str] = []
    members: list[str] = []
    seen: set[str] = set()
    for node in sorted(nodes, key=lambda n: (ROLES.index(n.role), n.name)):
        if node.name in seen:
            raise ValueError(f"{node.name!r} is named twice: a name is one certificate")
        seen.add(node.name)
        sid = f"{node.role}-{node.name}"
        subjects.append({"id": sid, "cert_common_names": [node.name]})
        if node.role == "router":
            routers.append(sid)
            continue
        own = agent_rules(node.name) if node.role == "agent" else station_rules(node.name)
        rules += own
        policies.append({"id": f"{sid}-policy", "rules": [r["id"] for r in own], "subjects": [sid]})
        members.append(sid)
    if members:
        policies.append(
            {"id": "members-learn", "rules": [r["id"] for r in SHARED_RULES], "subjects": members}
        )
    if routers:
        policies.append({"id": "routers", "rules": [r["id"] for r in ROUTER_RULES], "subjects": routers})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


__all__ = ["ROLES", "Node", "acl", "agent_rules", "station_rules"]
