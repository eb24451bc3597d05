"""Stations joined over Zenoh: this station's state out, the others' in, commands across.

Theory of operation
-------------------
:class:`Federation` is one Zenoh session (peer mode, connected to Zenoh routers or
other stations over IP: ``swarm gcs --radio ... --zenoh-connect tcp/ROUTER:7447``)
apart from the sessions that carry each radio's ``swarm/...`` key space, so the
agents' key space never leaves its channel. On it, under ``gcs/`` (the key space,
the envelope and what may cross are :mod:`swarm.core.station.federation`'s):

* a thread publishes ``local()`` (this station's agents, each with its ``net``,
  its events, swarms and alerts) on ``gcs/<name>/state`` every ``period`` seconds,
  each trail cut to the points a page draws (:data:`~swarm.core.station.federation.TRAIL_SENT`),
  shorter still if its JSON would not fit an envelope, deflated;
* a subscriber on ``gcs/*/state`` opens each envelope through a
  :class:`~swarm.core.station.federation.Gate` (signature, replay) and keeps each other
  station's cleaned state with the time it came (:meth:`remotes`): one silent for
  ``timeout`` seconds is *gone* (its agents shown disconnected), after
  ``forget`` seconds it is dropped. A state under our own name from another
  process, or under a name that is not its sender's, is a collision: one event,
  and the state is not taken;
* a queryable on ``gcs/<name>/command`` takes another station's command: opened
  by a gate that refuses unsigned commands unless told otherwise, then run by
  ``run_local`` (the station's own checks: parse, geofence, delivery on its
  radio) on the station's threads; the reply is a sealed result naming the
  request. At most :data:`MAX_IN_FLIGHT` commands wait at once (503 beyond);
* :meth:`request` sends a command to another station (``session.get`` on a
  worker thread) and gives its result as a future; no answer within
  ``command_timeout``: 504.

Callbacks run on Zenoh's threads; whatever a hostile sender puts there is counted
and dropped (``stats``), never raised into Zenoh. A state stamped too far ahead of
this station's clock is refused (:data:`~swarm.core.station.federation.FUTURE_S`) and said
once per sender as an event (a clock set wrong, or a forgery).

With a key and a ``state_file`` (the station's state folder), the gates' records
cross a restart (:meth:`~swarm.core.station.federation.Gate.records`): read at :meth:`start`
(a file that cannot be read is one warning line, and the gates start empty), written
atomically (:func:`radios.statefile.write_atomic`) when a command is taken, before it
is carried out (so one overheard on the router and replayed after a crash is still
one seen before), at most every 10 s when states came (a state replayed from those
seconds is superseded by the sender's next live one), and at :meth:`stop`. A save
that fails is one warning line (the command still runs: it is the operator's).
Without a key nothing is kept: anyone could forge what a record would guard against.
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import zenoh

from radios.statefile import read_state, write_atomic
from swarm.core.station.federation import (
    FUTURE_S,
    KIND_COMMAND,
    KIND_RESULT,
    KIND_STATE,
    MAX_ENVELOPE,
    PREFIX,
    TRAIL_SENT,
    Envelope,
    FederationRefused,
    Gate,
    Stamp,
    clean_result,
    clean_state,
    command_key,
    load_body,
    seal,
    state_key,
    thin,
)
from swarm.core.station.rows import StationState
from swarm.runtime.keyspace.transport import open_session

if TYPE_CHECKING:
    from swarm.runtime.options import TlsFiles

log = logging.getLogger(__name__)

MAX_IN_FLIGHT = 8
MAX_STATIONS = 32  # other stations kept at once: names beyond are refused (one event)
STATE_FORMAT = "uav-swarm station replay guard"
STATE_LIMIT = 2 * 1024 * 1024  # bytes: 4096 commands and 256 senders are well under this
SAVE_S = 10.0  # states taken are saved at most this often (commands: each, at once)

Result = tuple[int, dict[str, Any]]


@dataclass
class Remote:
    """Another station as last heard: its cleaned state and when (``clock``)."""

    name: str
    state: StationState
    heard: float
    instance: int


class Federation:
    """This station on the stations' Zenoh network (see the module docstring).

    ``local()`` gives the state to publish; ``run_local(body)`` carries out a command
    object for one of this station's agents (a future of (status, body); it raises
    :class:`~swarm.core.station.commands.CommandRefused`); ``on_event(kind, text)``
    is told of collisions and refusals worth an operator's eye.
    """

    def __init__(
        self,
        name: str,
        *,
        connect: Sequence[str] = (),
        listen: Sequence[str] = (),
        key: bytes | None = None,
        tls: TlsFiles | None = None,
        acl: str | None = None,
        accept_unsigned_commands: bool = False,
        local: Callable[[], StationState],
        run_local: Callable[[Any], Future[Result]],
        on_event: Callable[[str, str], None] = lambda kind, text: None,
        period: float = 0.5,
        timeout: float = 3.0,
        forget: float = 30.0,
        command_timeout: float = 18.0,  # inside the server's 20 s: its answer, not a 504
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        state_file: str | None = None,
    ) -> None:
        self.name = name
        self.connect, self.listen = tuple(connect), tuple(listen)
        self.key = key
        self.tls, self.acl = tls, acl
        self.local, self.run_local, self.on_event = local, run_local, on_event
        self.period, self.timeout, self.forget = period, timeout, forget
        self.command_timeout = command_timeout
        self.clock, self.wall = clock, wall
        self.instance = secrets.randbits(32)
        self.state_gate = Gate(key)
        self.command_gate = Gate(key, accept_unsigned_commands=accept_unsigned_commands)
        self.result_gate = Gate(key)
        self.stamp = Stamp()
        self.stats = {"published": 0, "states": 0, "refused": 0, "commands_in": 0, "commands_out": 0}
        self.stats["bytes"] = 0  # the states' bytes this station sent
        self._lock = threading.Lock()
        self._gates = threading.Lock()  # a gate's replay record: one envelope at a time
        self._remotes: dict[str, Remote] = {}
        self._said: set[str] = set()
        self._in_flight = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.session: Any = None
        self._decls: list[Any] = []
        self.state_file = state_file if key is not None else None  # unsigned: nothing worth keeping
        self._saved_at = 0.0
        self._saved_taken = -1
        self._save_failing = False
        self._save_lock = threading.Lock()

    # -- the gates' record across restarts -------------------------------------------------
    def _gates_by_name(self) -> dict[str, Gate]:
        return {"states": self.state_gate, "commands": self.command_gate, "results": self.result_gate}

    def load(self) -> None:
        """The replay guard's gates from its file (none: they start empty; a bad file: one warning)."""
        if self.state_file is None:
            return
        try:
            obj = read_state(self.state_file, STATE_LIMIT)
            if obj.get("format") != STATE_FORMAT or obj.get("version") != 1:
                raise ValueError("not a station replay guard of this version")
            wall = self.wall()
            with self._gates:
                for name, gate in self._gates_by_name().items():
                    gate.restore(obj.get(name), wall)
        except FileNotFoundError:
            return
        except (ValueError, FederationRefused) as exc:
            log.warning(
                "federation state %s ignored (%s): commands taken before this start are not remembered",
                self.state_file,
                exc,
            )

    def save(self) -> bool:
        """Write the gates' record now (False, one warning line, if it cannot be)."""
        if self.state_file is None:
            return False
        with self._save_lock:
            wall = self.wall()
            with self._gates:
                taken = sum(g.taken for g in self._gates_by_name().values())
                body = {name: g.records(wall) for name, g in self._gates_by_name().items()}
            data = json.dumps({"format": STATE_FORMAT, "version": 1, **body}, separators=(",", ":"))
            try:
                write_atomic(self.state_file, data.encode())
            except OSError as exc:
                if not self._save_failing:
                    log.warning(
                        "federation state %s not saved (%s): a command overheard before a restart "
                        "could be carried out again after it",
                        self.state_file,
                        exc.strerror or exc,
                    )
                self._save_failing = True
                return False
            if self._save_failing:
                log.warning("federation state %s saved again", self.state_file)
            self._save_failing = False
            self._saved_at, self._saved_taken = self.clock(), taken
            return True

    def _save_if_changed(self) -> None:
        if self.state_file is None or self.clock() - self._saved_at < SAVE_S:
            return
        with self._gates:
            taken = sum(g.taken for g in self._gates_by_name().values())
        if taken != self._saved_taken:
            self.save()

    # -- life cycle ---------------------------------------------------------------------
    def start(self) -> Federation:
        """Open the session and start publishing. Raises TransportError (endpoints) or
        CertError (the TLS or ACL files)."""
        self.load()
        self.session = open_session(
            self.listen, self.connect, tls=self.tls, acl=self.acl, signed=self.key is not None
        )
        try:
            self._decls.append(self.session.declare_subscriber(f"{PREFIX}/*/state", self._on_state))
            self._decls.append(self.session.declare_queryable(command_key(self.name), self._on_query))
        except BaseException:
            self.session.close()
            raise
        self._thread = threading.Thread(target=self._publish_loop, name="gcs-federation", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop publishing and close the session. Safe twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        session, self.session = self.session, None
        if session is not None:
            for d in self._decls:
                try:
                    d.undeclare()
                except Exception:
                    log.debug("federation: undeclare failed", exc_info=True)
            try:
                session.close()
            except Exception:
                log.debug("federation: close failed", exc_info=True)
            self.save()

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def describe(self) -> str:
        parts = [f"listen={','.join(self.listen)}"] if self.listen else []
        parts += [f"connect={','.join(self.connect)}"] if self.connect else []
        return (
            "stations "
            + " ".join(parts)
            + (" signed" if self.key else " unsigned")
            + (" tls" if self.tls else "")
        )

    # -- out ------------------------------------------------------------------------------
    def _seal(self, kind: bytes, body: Any) -> tuple[int, bytes]:
        return self._seal_json(kind, json.dumps(body, separators=(",", ":")).encode())

    def _seal_json(self, kind: bytes, data: bytes) -> tuple[int, bytes]:
        with self._lock:
            t = self.stamp.next(self.wall())
        return t, seal(kind, self.name, self.instance, t, data, self.key, deflate=kind == KIND_STATE)

    def _publish_loop(self) -> None:
        while not self._stop.wait(self.period):
            try:
                body = thin(self.local(), TRAIL_SENT)
                text = json.dumps(body, separators=(",", ":")).encode()
                if len(text) > MAX_ENVELOPE - 1024:  # hundreds of agents: inflated, it must fit
                    text = json.dumps(thin(body), separators=(",", ":")).encode()
                _t, data = self._seal_json(KIND_STATE, text)
                self.session.put(state_key(self.name), data)
                self.stats["published"] += 1
                self.stats["bytes"] += len(data)
            except Exception:
                log.debug("federation: publish failed", exc_info=True)
            self._save_if_changed()

    def request(self, station: str, body: dict[str, Any]) -> Future[Result]:
        """Send command object ``body`` to ``station``; its (status, body) as a future."""
        fut: Future[Result] = Future()
        threading.Thread(target=self._request, args=(station, body, fut), daemon=True).start()
        return fut

    def _request(self, station: str, body: dict[str, Any], fut: Future[Result]) -> None:
        try:
            self.stats["commands_out"] += 1
            t, data = self._seal(KIND_COMMAND, {"to": station, "command": body})
            session = self.session
            if session is None:
                fut.set_result((503, {"ok": False, "error": "the station is stopping"}))
                return
            # every queryable on the key (a hostile one too: its reply fails the result gate)
            replies = session.get(
                command_key(station), payload=data, timeout=self.command_timeout, target=zenoh.QueryTarget.ALL
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    env = self._open(self.result_gate, reply.ok.payload.to_bytes(), KIND_RESULT)
                    if env.sender != station:
                        raise FederationRefused(f"malformed: a result from {env.sender}, not {station}")
                    fut.set_result(clean_result(load_body(env.body), self.name, t))
                    return
                except FederationRefused as exc:
                    self._refused(f"a result from {station}", exc)
            fut.set_result((504, {"ok": False, "error": f"no answer from station {station}"}))
        except Exception as exc:
            log.debug("federation: request failed", exc_info=True)
            if not fut.done():
                fut.set_result((502, {"ok": False, "error": f"station {station}: {type(exc).__name__}"}))

    # -- in -------------------------------------------------------------------------------
    def _open(self, gate: Gate, data: bytes, kind: bytes) -> Envelope:
        with self._gates:
            return gate.open(data, self.wall(), kind)

    def _refused(self, what: str, exc: FederationRefused) -> None:
        self.stats["refused"] += 1
        log.debug("federation: %s refused: %s", what, exc)
        text = str(exc)
        if text.startswith("from the future: from "):  # a clock set wrong, or a forgery: said once
            sender, _sep, ahead = text.removeprefix("from the future: from ").partition(", ")
            self._say(
                f"future/{sender}",
                f"a state from station {sender} stamped {ahead} ahead of this station's clock "
                f"was refused (more than {FUTURE_S:g} s: a clock set wrong, or a forgery)",
            )

    def _on_state(self, sample: Any) -> None:
        try:
            key = str(sample.key_expr)
            env = self._open(self.state_gate, sample.payload.to_bytes(), KIND_STATE)
            owner = key.split("/")[1]
            if env.sender == self.name or owner != env.sender:
                if env.instance != self.instance or owner != env.sender:
                    self._collision(env.sender, owner)
                return
            state = clean_state(load_body(env.body))
            now = self.clock()
            with self._lock:
                old = self._remotes.get(env.sender)
                full = old is None and len(self._remotes) >= MAX_STATIONS
                if old is not None and old.instance != env.instance and now - old.heard < self.timeout:
                    fresh = False  # two processes under one name: keep the first, say so
                elif full:
                    fresh = True  # not kept: too many stations (said below)
                else:
                    self._remotes[env.sender] = Remote(env.sender, state, now, env.instance)
                    fresh = True
            if not fresh:
                self._collision(env.sender, owner)
            if full:
                self._say("full", f"more than {MAX_STATIONS} stations: {env.sender} and later ones ignored")
            self.stats["states"] += 1
        except FederationRefused as exc:
            self._refused("a state", exc)
        except Exception:
            self.stats["refused"] += 1
            log.debug("federation: a state failed", exc_info=True)

    def _collision(self, sender: str, owner: str) -> None:
        if sender != owner:
            text = f"station {sender} published under {owner}'s name: ignored"
        else:
            text = f"another station is also called {sender}: its state ignored (give each its own --name)"
        self._say(f"{sender}/{owner}", text)

    def _say(self, tag: str, text: str) -> None:
        """One event per ``tag``, for at most :data:`MAX_STATIONS` tags (names made up
        by the thousand are not remembered one by one)."""
        with self._lock:
            if tag in self._said or len(self._said) >= MAX_STATIONS:
                return
            self._said.add(tag)
        self.on_event("federation", text)

    def remotes(self) -> list[tuple[Remote, bool]]:
        """Every other station heard in the last ``forget`` seconds, with whether it is
        alive (heard in the last ``timeout``), by name."""
        now = self.clock()
        with self._lock:
            for n in [n for n, r in self._remotes.items() if now - r.heard > self.forget]:
                del self._remotes[n]
            return [(r, now - r.heard <= self.timeout) for _, r in sorted(self._remotes.items())]

    def _on_query(self, query: Any) -> None:
        try:
            payload = query.payload
            env = self._open(
                self.command_gate, payload.to_bytes() if payload is not None else b"", KIND_COMMAND
            )
        except FederationRefused as exc:
            self._refused("a command", exc)
            query.drop()
            return
        except Exception:
            log.debug("federation: a command failed", exc_info=True)
            query.drop()
            return
        self.stats["commands_in"] += 1
        self.save()  # taken: remembered across a restart before it is carried out
        answer = self._answer(query, env.sender, env.t_us)
        try:
            body = load_body(env.body)
            if not isinstance(body, dict) or body.get("to") != self.name:
                raise FederationRefused("malformed: a command for another station")
            with self._lock:
                busy = self._in_flight >= MAX_IN_FLIGHT
                self._in_flight += 0 if busy else 1
            if busy:
                answer((503, {"ok": False, "error": f"station {self.name} is busy: try again"}))
                return
            fut = self.run_local(body.get("command"))
        except FederationRefused as exc:
            answer((400, {"ok": False, "error": str(exc)}))
            return
        except Exception as exc:  # CommandRefused: the status it names
            answer(
                (
                    getattr(exc, "status", 500),
                    {"ok": False, "error": getattr(exc, "reason", type(exc).__name__)},
                )
            )
            self._done()
            return

        def finished(f: Future[Result]) -> None:
            answer(f.result())
            self._done()

        fut.add_done_callback(finished)

    def _done(self) -> None:
        with self._lock:
            self._in_flight -= 1

    def _answer(self, query: Any, sender: str, t_us: int) -> Callable[[Result], None]:
        def answer(result: Result) -> None:
            status, out = result
            try:
                _t, data = self._seal(KIND_RESULT, {"to": sender, "req": t_us, "status": status, "body": out})
                query.reply(query.key_expr, data)
            except Exception:
                log.debug("federation: a reply failed", exc_info=True)
            finally:
                query.drop()

        return answer


__all__ = ["MAX_IN_FLIGHT", "Federation", "Remote"]
