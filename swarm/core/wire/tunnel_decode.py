"""The swarm's TUNNEL payloads read back for people: kind, addressees and fields.

Theory of operation
-------------------
A capture holds the swarm's messages as MAVLink TUNNEL frames (:mod:`swarm.core.wire.tunnel`).
:func:`decode_tunnel` turns one frame's payload into a plain dict a person or a script
can read (``swarm replay`` prints it as a line of text or a JSON object)::

    {"tunnel": "p2p", "kind": "Heartbeat", "to": [2, 3],
     "fields": {"sender": 1, "epoch": 4, "seq": 17, "members": [2, 3], "task": {...}}}

``tunnel`` is the frame's kind (advertize, gs_advertize, p2p, pose, state, multi),
``to`` the addressees (``[0]``: everyone, as MAVLink's target 0), ``kind`` the
message's type and ``fields`` its values in JSON's types (enums by name, id sets as
sorted lists, poses and tasks as objects). A capture is hostile input: a payload
that does not decode (a cut or padded message, an unknown type, another protocol
version, an addressee list longer than the payload) gives ``kind`` None and
``error`` the one-line reason, never an exception. A payload type that is not the
swarm's gives None: the frame is someone else's and is shown as MAVLink.

:func:`format_fields` is the text form of ``fields``. Pure: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import fields as dc_fields
from dataclasses import is_dataclass
from enum import IntEnum
from typing import Any

from swarm.core.wire.messages import decode as decode_message
from swarm.core.wire.tunnel import Kind, unpack_tunnel
from swarm.errors import DecodeError

_TUNNEL_NAMES = {k: k.name.lower() for k in Kind}


_NAMES: dict[type, tuple[str, ...]] = {}


def _names(cls: type) -> tuple[str, ...]:
    """A dataclass's field names (looked up once per class)."""
    names = _NAMES.get(cls)
    if names is None:
        names = _NAMES[cls] = tuple(f.name for f in dc_fields(cls))
    return names


_SCALARS = frozenset({int, float, str, bool, type(None)})


def _plain(v: Any) -> Any:
    """``v`` in JSON's types: enums by name, sets sorted, dataclasses as objects."""
    t = type(v)
    if t in _SCALARS:  # the common case first: this runs for every field of every frame
        return v
    if isinstance(v, IntEnum):
        return v.name
    if isinstance(v, frozenset | set):
        return sorted(v)
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    if is_dataclass(v) and not isinstance(v, type):
        return {n: _plain(getattr(v, n)) for n in _names(t)}
    return str(v)


def decode_tunnel(payload: bytes) -> dict[str, Any] | None:
    """One TUNNEL frame's payload (the MAVLink message's bytes: payload_type,
    target_system, target_component, payload_length, payload) as a dict (see the
    module's text), or None when its payload type is not the swarm's. Never raises."""
    try:
        tun = unpack_tunnel(payload)
    except DecodeError as exc:  # MULTI with an addressee list that does not fit
        return {"tunnel": _TUNNEL_NAMES[Kind.MULTI], "kind": None, "to": [], "fields": {}, "error": str(exc)}
    if tun is None:
        return None
    kind, target, ids, data = tun
    to = sorted(set(ids)) if kind == Kind.MULTI else [target]
    out: dict[str, Any] = {"tunnel": _TUNNEL_NAMES[kind], "kind": None, "to": to, "fields": {}}
    try:
        msg = decode_message(data)
    except DecodeError as exc:
        out["error"] = f"{len(data)} bytes: {exc}"
        return out
    out["kind"] = type(msg).__name__
    out["fields"] = {n: _plain(getattr(msg, n)) for n in _names(type(msg))}
    return out


def _text(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.7g}"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} : {_text(x)}" for k, x in v.items()) + "}"
    if isinstance(v, list):
        return "[" + ", ".join(_text(x) for x in v) + "]"
    return str(v)


def format_fields(fields: dict[str, Any]) -> str:
    """``fields`` of :func:`decode_tunnel` as ``{name : value, ...}`` (MAVProxy's way)."""
    return "{" + ", ".join(f"{k} : {_text(v)}" for k, v in fields.items()) + "}"


def format_to(to: list[int]) -> str:
    """The addressees for a text line: ``all`` for ``[0]``, else ``1,2,3``."""
    return "all" if to == [0] else ",".join(map(str, to)) or "-"


__all__ = ["decode_tunnel", "format_fields", "format_to"]
