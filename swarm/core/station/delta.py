"""State deltas for the ground station's WebSocket: what changed between two snapshots.

Theory of operation
-------------------
The station's state (:meth:`swarm.core.station.core.StationCore.snapshot`, with the
station's own description) is a JSON object: a few top-level fields (``time``,
``leader``, ``station``...), ``agents`` (one object per agent, each with its
``trail`` of ``[lat, lon]`` points) and ``events`` (the newest station events).
Sent whole at every push it is ~150 KB at 50 agents with full trails, nearly all of
it unchanged since the previous push. :func:`build` says what changed from ``old``
to ``new``; :func:`apply` turns ``old`` and that delta back into ``new``, exactly
(same keys, same values, same order of agents): the page mirrors :func:`apply` in
``static/delta.js``.

A delta is a JSON object with only the parts that changed:

* ``set``: top-level fields (other than ``agents`` and ``events``) whose value
  changed or that are new; ``unset``: top-level fields gone;
* ``agents``: an object with one patch per agent that changed or is new, under its
  id as text: ``{"7": {field: value...}}`` for each field whose value changed (a
  new agent: every field, its ``id`` too), and ``"unset": [field...]`` for fields
  gone; its trail as ``"trail": [cut, keep, point...]``: drop ``cut`` points from
  the front, keep the next ``keep``, then append the points (a point written ``0``
  is the agent's own ``[lat, lon]`` after the patch: the newest trail point is
  nearly always the agent's position, so a trail that moved on costs ``[0,119,0]``);
* ``drop``: ids of agents gone; ``order``: the agents' ids in order, only when that
  is not ascending ids (the station always sends them sorted);
* ``events``: ``[cut, keep, event...]`` as for a trail (the station keeps the
  newest N events: a new one pushes the oldest out);
* ``alerts``: the alarms that changed, by key (``"<station>:<id>"``, the station
  empty for this station's own: :func:`alert_key`), as ``{"set": {key: patch...},
  "drop": [key...], "order": [key...]}``, each part only when needed: a patch as an
  agent's (the fields that changed, ``unset``; a new alarm's every field), ``order``
  only when the alarms are not those kept in their order followed by the new ones in
  theirs. A flapping link's alarm costs its count and time, not the whole list.

A list edit ``[cut, keep, added...]`` is exact for any two lists (``new ==
old[cut:cut + keep] + added``); :func:`list_delta` looks for the alignment that keeps the
most (``new[0]``'s first place in ``old``), so a trail that moved on by one point
costs one or two points, whatever its length. Values compare by type and value
(``True`` is not ``1``, ``-0.0`` is not ``0.0``), so a delta never turns a JSON
``true`` into ``1``; inside a list (a trail point, a list of ids) items compare
by ``==`` and their types one level deep, which keeps 120-point trails cheap.

Pure: no I/O, no clock. The WebSocket's sequence numbers and resyncs are
:mod:`swarm.runtime.station.websocket`'s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

#: the state's list-valued top-level fields that travel as their own edits
AGENTS = "agents"
EVENTS = "events"
ALERTS = "alerts"
TRAIL = "trail"


class DeltaError(ValueError):
    """A delta that does not fit the state it is applied to (a client should resync)."""


def same(a: Any, b: Any) -> bool:
    """Equal as JSON: same type and value (``True`` is not ``1``, ``1`` is not ``1.0``).
    A list compares its items with ``==`` and their types one level deep (a trail
    point, a list of ids), which keeps a trail of 120 points cheap to compare."""
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(v, b[k]) for k, v in a.items())
    if isinstance(a, list):
        return a == b and all(type(x) is type(y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and a == 0.0:
        return b == 0.0 and math.copysign(1.0, a) == math.copysign(1.0, b)  # -0.0 is written "-0.0"
    return bool(a == b)


def list_delta(old: list[Any], new: list[Any]) -> list[Any] | None:
    """``[cut, keep, added...]`` with ``new == old[cut:cut + keep] + added``; None if equal."""
    if same(old, new):
        return None
    if not new:
        return [len(old), 0]
    cut = _index(old, new[0])
    if cut is None:
        return [len(old), 0, *new]
    rest = len(old) - cut
    if rest <= len(new) and same(old[cut:], new[:rest]):
        keep = rest
    else:
        keep = 0
        limit = min(rest, len(new))
        while keep < limit and same(old[cut + keep], new[keep]):
            keep += 1
    return [cut, keep, *new[keep:]]


def _index(xs: list[Any], x: Any) -> int | None:
    for i, y in enumerate(xs):
        if same(y, x):
            return i
    return None


def apply_list(old: list[Any], edit: Any, what: str) -> list[Any]:
    """``old`` edited by ``[cut, keep, added...]``.

    Raises:
        DeltaError: a malformed edit, or one that does not fit ``old``.
    """
    if not (isinstance(edit, list) and len(edit) >= 2):
        raise DeltaError(f"{what}: an edit is [cut, keep, item...]")
    cut, keep = edit[0], edit[1]
    if not (_count(cut) and _count(keep) and cut + keep <= len(old)):
        raise DeltaError(f"{what}: edit [{cut!r}, {keep!r}] does not fit {len(old)} items")
    return old[cut : cut + keep] + edit[2:]


def _count(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def build(old: Mapping[str, Any], new: Mapping[str, Any]) -> dict[str, Any]:
    """The delta from ``old`` to ``new`` (two states as the station's snapshot gives them)."""
    d: dict[str, Any] = {}
    _fields(old, new, (AGENTS, EVENTS, ALERTS), d, "set")
    ev = list_delta(old.get(EVENTS, []), new.get(EVENTS, []))
    if ev is not None:
        d[EVENTS] = ev
    if ALERTS in new:
        al = alerts_delta(old.get(ALERTS, []), new[ALERTS]) if ALERTS in old else {"set": _keyed(new[ALERTS])}
        if al is not None:
            d[ALERTS] = al
    elif ALERTS in old:
        d.setdefault("unset", []).append(ALERTS)
    before = {a["id"]: a for a in old.get(AGENTS, [])}
    ids = [a["id"] for a in new.get(AGENTS, [])]
    patches = {}
    for a in new.get(AGENTS, []):
        p = agent_patch(before.get(a["id"]), a)
        if p is not None:
            patches[str(a["id"])] = p
    if patches:
        d[AGENTS] = patches
    now = set(ids)
    drop = [i for i in before if i not in now]
    if drop:
        d["drop"] = drop
    if ids != sorted(ids):
        d["order"] = ids
    return d


def _fields(
    old: Mapping[str, Any], new: Mapping[str, Any], skip: tuple[str, ...], d: dict[str, Any], key: str
) -> None:
    changed = {k: v for k, v in new.items() if k not in skip and (k not in old or not same(old[k], v))}
    if changed:
        d[key] = changed
    gone = [k for k in old if k not in new and k not in skip]
    if gone:
        d["unset"] = gone


def alert_key(a: Mapping[str, Any]) -> str:
    """An alarm's key in a delta: ``"<station>:<id>"`` (ids are per station)."""
    return f"{a.get('station') or ''}:{a.get('id')}"


def _keyed(rows: list[Any]) -> dict[str, Any]:
    return {alert_key(a): dict(a) for a in rows}


def alerts_delta(old: list[Any], new: list[Any]) -> dict[str, Any] | None:
    """The alarms' part of a delta (module docstring); None: unchanged."""
    before = {alert_key(a): a for a in old}
    keys = [alert_key(a) for a in new]
    d: dict[str, Any] = {}
    patches = {}
    for k, a in zip(keys, new, strict=True):
        p = agent_patch(before.get(k), a)
        if p is not None:
            patches[k] = p
    if patches:
        d["set"] = patches
    now = set(keys)
    drop = [k for k in before if k not in now]
    if drop:
        d["drop"] = drop
    natural = [k for k in before if k in now] + [k for k in keys if k not in before]
    if keys != natural:
        d["order"] = keys
    return d or None


def apply_alerts(old: list[Any], edit: Any) -> list[Any]:
    """The alarms ``old`` with their part of a delta applied (new dicts where patched)."""
    if not isinstance(edit, dict):
        raise DeltaError("alerts: an object of set, drop, order")
    items = {alert_key(a): a for a in old}
    for k in edit.get("drop", []):
        if items.pop(k, None) is None:
            raise DeltaError(f"alerts: drop {str(k)[:20]!r}: no such alarm")
    patches = edit.get("set", {})
    if not isinstance(patches, dict):
        raise DeltaError("alerts: set is an object of patches by key")
    for k, p in patches.items():
        base = items.get(k)
        if not isinstance(p, dict) or (base is None and alert_key(p) != k):
            raise DeltaError(f"alerts: {str(k)[:20]!r}: a patch is an object (a new alarm's whole)")
        a = {f: v for f, v in (base or {}).items() if f not in p.get("unset", [])}
        a.update({f: v for f, v in p.items() if f != "unset"})
        items[k] = a
    order = edit.get("order")
    keys = order if order is not None else list(items)
    if not isinstance(keys, list) or len(keys) != len(items) or any(k not in items for k in keys):
        raise DeltaError("alerts: the order does not name every alarm")
    return [items[k] for k in keys]


def agent_patch(old: Mapping[str, Any] | None, new: Mapping[str, Any]) -> dict[str, Any] | None:
    """One agent's patch (None: unchanged); ``old`` None: a new agent, every field."""
    p: dict[str, Any] = {}
    base = old if old is not None else {}
    for k, v in new.items():
        if k != TRAIL and (k not in base or not same(base[k], v)):
            p[k] = v
    gone = [k for k in base if k not in new]
    if gone:
        p["unset"] = gone
    if TRAIL in new:
        edit = list_delta(base.get(TRAIL, []), new[TRAIL]) if TRAIL in base else [0, 0, *new[TRAIL]]
        if edit is not None:
            here = [new.get("lat"), new.get("lon")]
            p[TRAIL] = edit[:2] + [0 if same(pt, here) else pt for pt in edit[2:]]
    return p or None


def apply(old: dict[str, Any], delta: dict[str, Any]) -> dict[str, Any]:
    """``old`` with ``delta`` applied (a new state; ``old`` is left as it was).

    Raises:
        DeltaError: a delta that does not fit ``old`` (the client should ask for the
            whole state again).
    """
    st = {k: v for k, v in old.items() if k not in delta.get("unset", [])}
    st.update(delta.get("set", {}))
    if EVENTS in delta:
        st[EVENTS] = apply_list(old.get(EVENTS, []), delta[EVENTS], EVENTS)
    if ALERTS in delta:
        st[ALERTS] = apply_alerts(old.get(ALERTS, []), delta[ALERTS])
    agents = {a["id"]: a for a in old.get(AGENTS, [])}
    for i in delta.get("drop", []):
        if agents.pop(i, None) is None:
            raise DeltaError(f"drop: no agent {i!r}")
    patches = delta.get(AGENTS, {})
    if not isinstance(patches, dict):
        raise DeltaError("agents: an object of patches by id")
    for key, p in patches.items():
        aid = _agent_id(key)
        agents[aid] = apply_agent(agents.get(aid), p, aid)
    order = delta.get("order")
    ids = order if order is not None else sorted(agents)
    if len(ids) != len(agents) or any(i not in agents for i in ids):
        raise DeltaError("the agents' order does not name every agent")
    if AGENTS in old or agents:
        st[AGENTS] = [agents[i] for i in ids]
    return st


def _agent_id(key: Any) -> int:
    if not (isinstance(key, str) and key.isdigit() and len(key) <= 9):
        raise DeltaError(f"agents: {str(key)[:20]!r} is not an agent id")
    return int(key)


def apply_agent(old: dict[str, Any] | None, p: Any, aid: int) -> dict[str, Any]:
    """One agent's patch applied (a new dict)."""
    if not isinstance(p, dict) or (old is None and p.get("id") != aid):
        raise DeltaError(f"agent {aid}: a patch is an object (a new agent's with its id)")
    base = old if old is not None else {}
    a = {k: v for k, v in base.items() if k not in p.get("unset", [])}
    for k, v in p.items():
        if k not in ("unset", TRAIL):
            a[k] = v
    if TRAIL in p:
        here = [a.get("lat"), a.get("lon")]
        pts = apply_list(base.get(TRAIL, []), p[TRAIL], f"agent {aid} trail")
        a[TRAIL] = [list(here) if pt == 0 and not isinstance(pt, bool) else pt for pt in pts]
    return a
