"""``swarm certs``: the swarm's certificate authority, node certificates and ACL file.

Theory of operation
-------------------
Zenoh over IP is authenticated by mutual TLS and authorised by Zenoh's access control
(docs/security.md, "Zenoh over IP"); this command makes what both need, in one folder kept on
the machine where certificates are made (the CA's private key never leaves it):

* ``swarm certs ca DIR [--days N]``: the CA, ``DIR/ca.key`` (0600) and ``DIR/ca.pem``;
* ``swarm certs node DIR NAME --role agent|station|router [--host H ...] [--days N]``:
  ``DIR/NAME.key`` (0600) and ``DIR/NAME.pem`` signed by the CA, the certificate's
  common name the node's name (an agent's ``--name``, a station's ``--name``), its
  unit the role; ``--host`` adds the addresses or names others connect to (a router's,
  a listening station's: Zenoh checks them); then ``DIR/acl.json5`` is written anew
  for every node the CA signed;
* ``swarm certs acl DIR [--out FILE]``: the ACL file again (after removing a node's
  certificate, say).

Nothing existing is overwritten but the ACL file (derived from the certificates); the
folder must exist. The work is :mod:`swarm.runtime.keyspace.pki`'s and the rules are
:mod:`swarm.core.keyspace.acl`'s. Exit 0 with what to copy where, 2 for bad input (an
existing file, no folder, a bad name or role, no CA), 1 for a failed write.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from swarm.cli.util import guarded
from swarm.core.keyspace.acl import ROLES

PROG = "swarm certs"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="The swarm's own certificate authority, node certificates (mutual TLS for Zenoh "
        "over IP) and the Zenoh access-control file. Never overwrites a key or a certificate.",
    )
    sub = p.add_subparsers(dest="what", required=True, metavar="ca|node|acl")
    ca = sub.add_parser("ca", help="make the swarm's CA: DIR/ca.key (0600) and DIR/ca.pem")
    ca.add_argument("dir", metavar="DIR", help="the folder (must exist; keep it on one machine)")
    ca.add_argument("--days", type=int, default=3650, help="validity in days (default 3650)")
    node = sub.add_parser("node", help="a node's DIR/NAME.key and DIR/NAME.pem, then DIR/acl.json5 anew")
    node.add_argument("dir", metavar="DIR", help="the CA's folder")
    node.add_argument("name", metavar="NAME", help="the node's name: the agent's or station's --name")
    node.add_argument("--role", required=True, choices=ROLES, help="what the node may do (the ACL's rules)")
    node.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="H",
        help="an address or DNS name others connect to (routers, listening nodes; repeatable)",
    )
    node.add_argument("--days", type=int, default=365, help="validity in days (default 365)")
    acl = sub.add_parser("acl", help="write DIR/acl.json5 again from the certificates the CA signed")
    acl.add_argument("dir", metavar="DIR", help="the CA's folder")
    acl.add_argument("--out", metavar="FILE", help="write it here instead of DIR/acl.json5")
    return p


def _acl(folder: str, out: str | None = None) -> list[str]:
    from swarm.runtime.keyspace.pki import nodes, write_acl

    members, skipped = nodes(folder)
    path = write_acl(folder, members, out)
    by_role = {r: sorted(n.name for n in members if n.role == r) for r in ROLES}
    lines = [f"wrote {path}: " + "; ".join(f"{r}s {', '.join(v) or '-'}" for r, v in by_role.items())]
    lines += [f"skipped {s}" for s in skipped]
    return lines


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    from swarm.runtime.keyspace.pki import issue, make_ca

    a = build_parser().parse_args(argv)
    now = time.time()
    if a.what == "ca":
        key, cert = make_ca(a.dir, now=now, days=a.days)
        print(
            "\n".join(
                [
                    f"wrote the swarm's CA: {cert} (every node gets a copy) and {key} (mode 0600:",
                    "it signs new nodes; keep it here, never copy it to a node)",
                    f"next, one certificate per node: swarm certs node {a.dir} NAME "
                    "--role agent|station|router",
                ]
            ),
            flush=True,
        )
        return 0
    if a.what == "node":
        key, cert = issue(a.dir, a.name, a.role, now=now, hosts=a.host, days=a.days)
        lines = [f"wrote {cert} and {key} (mode 0600) for {a.role} {a.name}"]
        lines += _acl(a.dir)
        ca = Path(a.dir) / "ca.pem"
        flags = f"--tls-ca ca.pem --tls-cert {cert.name} --tls-key {key.name}"
        if a.role == "router":
            lines.append(
                f"copy {ca}, {cert}, {key} and the ACL file to the router (keep the key 0600: scp -p);"
            )
            lines.append(f"run: swarm router --listen tls/0.0.0.0:7447 {flags} --acl acl.json5")
        else:
            lines.append(f"copy {ca}, {cert} and {key} to {a.name} (keep the key 0600: scp -p);")
            lines.append(f"run it with {flags} and tls/ endpoints (--zenoh-connect tls/ROUTER:7447)")
        lines.append("the ACL file changed: copy it to every router (and listening node) and restart them")
        print("\n".join(lines), flush=True)
        return 0
    print("\n".join(_acl(a.dir, a.out)), flush=True)
    return 0
