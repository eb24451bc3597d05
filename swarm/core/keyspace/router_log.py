"""What a Zenoh router refused, read from Zenoh's own log lines: counted, said once each.

Theory of operation
-------------------
Zenoh (1.10) tells of refusals only in its log, which zenoh-python writes to
standard output (Rust's ``tracing``): a TLS handshake it refused at ``WARN``
(``zenoh_link_tls::unicast: invalid peer certificate: UnknownIssuer``, ``peer sent no
certificates``, ``certificate expired: ...``), and an access-control decision at
``TRACE`` (``zenoh::net::routing::interceptor::access_control: <zid> on
Interface(lo)+CertCommonName(agent1)+... is unauthorized to Put (ingress) on
swarm/agent2/command``, or ``Using cached result: <zid> is unauthorized to ...`` when it
decided the same before). :class:`ZenohLogReader` reads those lines (colours
stripped) into :class:`Refusal` values:

* a TLS refusal names why (no certificate, another CA's, expired, not yet valid, a
  name that does not match) but not who: Zenoh's line does not say;
* an access-control refusal names the certificate (its common name, or "a node
  without a certificate"), what it tried (put, query, declare_subscriber...), the
  flow (``ingress``: it sent it; ``egress``: the router kept it from it) and the key.
  Zenoh also logs, when a node first uses a key, what that node *would* be allowed
  for every kind of message ("caching permissions for `K`" then nine decisions on
  the same thread): those are not attempts and are skipped (their node's name is
  learnt from them for the "cached result" lines, which give only its id).

:class:`RefusalBook` counts them: :meth:`RefusalBook.note` says whether a refusal is
the first of its kind (the router logs it once), :meth:`RefusalBook.counts` gives all.
Other ``WARN`` and ``ERROR`` lines are returned as :class:`Passed` for the router to
show. Pure: lines in, values out; no I/O, no clock.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_LINE = re.compile(
    r"^\S+\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:\S+\s+)?ThreadId\((?P<tid>\d+)\)\s+"
    r"(?P<target>[\w:]+):\s(?P<msg>.*)$"
)
_CACHING = re.compile(r"^ACL \((?:ingress|egress)\): caching permissions for `(?P<key>[^`]*)`")
_DECISION = re.compile(
    r"^(?P<zid>[0-9a-f]+) on (?P<subject>\S+) is (?P<un>un)?authorized to (?P<action>.+?) "
    r"\((?P<flow>ingress|egress)\) on (?P<key>\S+)$"
)
_CACHED = re.compile(
    r"^Using cached result: (?P<zid>[0-9a-f]+) is (?P<un>un)?authorized to (?P<action>.+?) "
    r"\((?P<flow>ingress|egress)\) on (?P<key>\S+)$"
)
_CN = re.compile(r"CertCommonName\(([^)]*)\)")
#: Zenoh's names for what was tried, as the ACL file names them
ACTIONS = {
    "Put": "put",
    "Delete": "delete",
    "Query": "query",
    "Reply": "reply",
    "Declare/Undeclare Subscriber": "declare_subscriber",
    "Declare Subscriber": "declare_subscriber",
    "Declare/Undeclare Queryable": "declare_queryable",
    "Declare Queryable": "declare_queryable",
    "Declare/Undeclare Liveliness Token": "liveliness_token",
    "Liveliness Query": "liveliness_query",
    "Declare Liveliness Subscriber": "declare_liveliness_subscriber",
}
PRECOMPUTED = 9  # decisions Zenoh logs after "caching permissions for" (one per kind of message)
ANONYMOUS = "a node without a certificate"
_HINT = ". Hint: increase the system open file limit."


@dataclass(frozen=True)
class Refusal:
    """``by`` ``tls`` (a handshake: ``why``) or ``acl`` (``who`` tried ``what`` in
    ``flow`` on ``key``)."""

    by: str
    why: str = ""
    who: str = ""
    what: str = ""
    flow: str = ""
    key: str = ""

    def text(self) -> str:
        if self.by == "tls":
            return f"refused a TLS connection: {self.why}"
        verb = "tried to" if self.flow == "ingress" else "was kept from"
        return f"refused {self.who}: it {verb} {self.what} on {self.key} (access control)"

    def as_dict(self) -> dict[str, str]:
        if self.by == "tls":
            return {"by": "tls", "why": self.why}
        return {"by": "acl", "who": self.who, "what": self.what, "flow": self.flow, "key": self.key}


@dataclass(frozen=True)
class Passed:
    """A Zenoh warning or error the reader has no word for: ``level`` and text."""

    level: str
    text: str


def tls_reason(msg: str) -> str | None:
    """Why a TLS handshake was refused, in the swarm's words (None: not a refusal)."""
    m = msg.removesuffix(_HINT)
    low = m.lower()
    if "peer sent no certificates" in low:
        return "no client certificate"
    if "invalidcontenttype" in low:  # not a TLS record: a plain TCP client at a TLS port
        return "not TLS (a plain TCP client?)"
    if low.startswith("received fatal alert"):  # the client refused our certificate: not one of ours
        return f"a client without the swarm's CA ({m.rsplit(': ', 1)[-1]})"
    if not low.startswith(("invalid peer certificate", "can not accept tls connection", "received corrupt")):
        return None
    if "unknownissuer" in low or "unknown issuer" in low:
        return "a certificate of another CA (unknown issuer)"
    if "expired" in low:
        return "an expired certificate"
    if "notvalidyet" in low or "not valid yet" in low:
        return "a certificate not yet valid (a clock behind?)"
    if "notvalidforname" in low:
        return "a certificate for another name"
    if "badsignature" in low:  # rustls: a CA of the same name, not the same key
        return "a certificate of another CA, or forged (bad signature)"
    return m.split(": ", 1)[-1][:120]


class ZenohLogReader:
    """Zenoh's log lines in, :class:`Refusal` or :class:`Passed` (or None) out."""

    def __init__(self) -> None:
        self.names: dict[str, str] = {}  # zid -> its certificate's name
        self._block: dict[str, tuple[str, int]] = {}  # thread -> (key, decisions left)

    def line(self, raw: str) -> Refusal | Passed | None:
        m = _LINE.match(_ANSI.sub("", raw).rstrip())
        if m is None:
            return None
        level, tid, target, msg = m["level"], m["tid"], m["target"], m["msg"]
        if target.startswith("zenoh_link_tls"):
            why = tls_reason(msg)
            if why is not None:
                return Refusal("tls", why=why)
        elif target.endswith("access_control"):
            return self._acl(tid, msg)
        if level in ("WARN", "ERROR"):
            return Passed(level, f"{target}: {msg.removesuffix(_HINT)}")
        return None

    def _acl(self, tid: str, msg: str) -> Refusal | None:
        c = _CACHING.match(msg)
        if c is not None:
            self._block[tid] = (c["key"], PRECOMPUTED)
            return None
        d = _DECISION.match(msg)
        if d is not None:
            cn = _CN.search(d["subject"])
            who = cn.group(1) if cn else ANONYMOUS
            self.names[d["zid"]] = who
            key, left = self._block.get(tid, ("", 0))
            if left and key == d["key"]:
                self._block[tid] = (key, left - 1)
                return None  # what it would be allowed: not an attempt
            self._block.pop(tid, None)
            return self._refusal(d, who)
        cached = _CACHED.match(msg)
        if cached is not None:
            return self._refusal(cached, self.names.get(cached["zid"], f"node {cached['zid']}"))
        return None

    @staticmethod
    def _refusal(m: re.Match[str], who: str) -> Refusal | None:
        if not m["un"]:
            return None
        return Refusal(
            "acl", who=who, what=ACTIONS.get(m["action"], m["action"]), flow=m["flow"], key=m["key"]
        )


@dataclass
class RefusalBook:
    """Refusals counted by kind; the first of each kind is the one to log."""

    seen: dict[Refusal, int] = field(default_factory=dict)

    def note(self, r: Refusal) -> bool:
        """Count ``r``; True when it is the first of its kind."""
        n = self.seen.get(r, 0) + 1
        self.seen[r] = n
        return n == 1

    @property
    def total(self) -> int:
        return sum(self.seen.values())

    def counts(self) -> list[dict[str, object]]:
        return [{**r.as_dict(), "count": n} for r, n in self.seen.items()]


__all__ = ["ANONYMOUS", "Passed", "Refusal", "RefusalBook", "ZenohLogReader", "tls_reason"]
