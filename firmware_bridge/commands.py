"""COMMAND_LONG with acknowledgement and retries, as a pure state machine.

Theory of operation. A :class:`CommandExchange` is one command in flight. It is
made with the time it starts and returns, from :meth:`~CommandExchange.start`,
the first COMMAND_LONG to send (confirmation 0). It is then fed what the
autopilot says (:meth:`~CommandExchange.handle` with a :class:`CommandAck` or a
:class:`StatusText`, as :class:`~firmware_bridge.telemetry.TelemetryFolder`
returns them) and woken at :meth:`~CommandExchange.next_deadline` (:meth:`tick`).
The whole machine, per state:

* ``waiting`` (an ACK of this command): ACCEPTED -> done, :class:`Accepted`;
  IN_PROGRESS -> keep waiting, the try's deadline moved to ``max(per_try, 5 s)``
  from now but never past ``in_progress_timeout`` after that try was sent; any other
  result -> ``explaining``; the try's deadline -> the next try goes out
  (confirmation 1, 2 ...) or, after ``tries`` tries, done, :class:`TimedOut`.
* ``explaining`` (the refusal's reason): done, :class:`Rejected` with the
  autopilot's STATUSTEXTs since half a second before the first try that explain a
  refusal (:func:`is_reason`: a warning or worse, "PreArm:", "Arm:"...), as soon as
  there is one, or after a 0.3 s grace with whatever texts there are (autopilots
  send the reason just before or after the ACK: ArduCopter after, so an INFO boot
  text heard just before is not taken for it).
* ``done``: :attr:`~CommandExchange.outcome` is set; nothing more is sent.

ACKs of other commands are not this exchange's. No I/O, no clock: ``now`` comes
from the caller; the messages to send are returned, never sent here.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega

from firmware_bridge.errors import CommandRejected, CommandTimeout
from firmware_bridge.telemetry import MAV_SEVERITY_WARNING, CommandAck, StatusText

mavlink: Any = ardupilotmega

__all__ = [
    "Accepted",
    "CommandExchange",
    "Outcome",
    "Rejected",
    "TimedOut",
    "command_long",
    "command_name",
]

MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_NAV_LAND = 21
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
FORCE_MAGIC_PX4 = 21196  # force arm/disarm
FORCE_ARM_ARDUPILOT = 2989

MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
MAV_RESULT_NAMES = {
    0: "ACCEPTED",
    1: "TEMPORARILY_REJECTED",
    2: "DENIED",
    3: "UNSUPPORTED",
    4: "FAILED",
    5: "IN_PROGRESS",
    6: "CANCELLED",
}

_CMD_NAMES = {
    MAV_CMD_NAV_TAKEOFF: "NAV_TAKEOFF",
    MAV_CMD_DO_SET_MODE: "DO_SET_MODE",
    MAV_CMD_COMPONENT_ARM_DISARM: "COMPONENT_ARM_DISARM",
    MAV_CMD_SET_MESSAGE_INTERVAL: "SET_MESSAGE_INTERVAL",
    MAV_CMD_REQUEST_MESSAGE: "REQUEST_MESSAGE",
    MAV_CMD_NAV_LAND: "NAV_LAND",
    MAV_CMD_NAV_RETURN_TO_LAUNCH: "NAV_RETURN_TO_LAUNCH",
}

IN_PROGRESS_EXTENSION_S = 5.0  # an IN_PROGRESS ACK buys at least this long
TEXT_BEFORE_S = 0.5  # a STATUSTEXT this long before the first try still explains a refusal
TEXT_GRACE_S = 0.3  # how long a refusal waits for its STATUSTEXT


#: STATUSTEXT openings that give an autopilot's reasons for refusing to arm
ARMING_TEXTS = ("PreArm:", "Arm:", "Preflight Fail", "Arming denied")


def is_reason(text: StatusText) -> bool:
    """A text that explains a refusal: a warning or worse, or a refusal's own opening
    (an INFO "ArduPilot Ready" or "AHRS: DCM active" heard meanwhile does not)."""
    return text.severity <= MAV_SEVERITY_WARNING or text.text.startswith(ARMING_TEXTS)


def command_name(command: int) -> str:
    """``NAV_TAKEOFF``, ... or ``command N`` for a command id."""
    return _CMD_NAMES.get(command, f"command {command}")


def command_long(
    command: int, params: Sequence[float], confirmation: int, *, target_system: int, target_component: int
) -> Any:
    """The COMMAND_LONG message: up to 7 parameters (the rest 0)."""
    p = [float(x) for x in params] + [0.0] * (7 - len(params))
    return mavlink.MAVLink_command_long_message(target_system, target_component, command, confirmation, *p)


@dataclass(frozen=True)
class Accepted:
    """The autopilot accepted the command."""


@dataclass(frozen=True)
class Rejected:
    """The autopilot refused the command: ``result`` (MAV_RESULT), ``text`` its reason."""

    result: int
    text: str


@dataclass(frozen=True)
class TimedOut:
    """No final ACK after ``tries`` tries of ``per_try`` s each."""

    tries: int
    per_try: float


Outcome = Accepted | Rejected | TimedOut


class CommandExchange:
    """One COMMAND_LONG in flight (see the module header for the machine).

    ``tries`` (at least 1) tries of ``per_try`` s each; an IN_PROGRESS ACK waits up
    to ``in_progress_timeout`` s after its try. ``texts`` are the STATUSTEXTs heard
    before the start (only those from ``TEXT_BEFORE_S`` before it count).
    """

    def __init__(
        self,
        command: int,
        params: Sequence[float],
        now: float,
        *,
        target_system: int,
        target_component: int,
        tries: int,
        per_try: float,
        in_progress_timeout: float = 30.0,
        texts: Iterable[StatusText] = (),
    ) -> None:
        self.command = command
        self.params = tuple(params)
        self.target = (target_system, target_component)
        self.tries = max(1, tries)
        self.per_try = per_try
        self.in_progress_timeout = in_progress_timeout
        self.started = now
        self.state = "waiting"
        self.outcome: Outcome | None = None
        self.attempt = 0
        self._texts = [t for t in texts if t.time >= now - TEXT_BEFORE_S]
        self._deadline = now + per_try
        self._hard_deadline = now + in_progress_timeout
        self._result = 0

    def start(self) -> Any:
        """The first COMMAND_LONG to send (confirmation 0)."""
        return self._message()

    def _message(self) -> Any:
        return command_long(
            self.command,
            self.params,
            min(self.attempt, 255),
            target_system=self.target[0],
            target_component=self.target[1],
        )

    def next_deadline(self) -> float | None:
        """When :meth:`tick` must run next; None once done."""
        return None if self.outcome is not None else self._deadline

    def handle(self, event: CommandAck | StatusText, now: float) -> None:
        """Feed an ACK or a STATUSTEXT from the autopilot, heard at ``now``."""
        if isinstance(event, StatusText):
            if event.time >= self.started - TEXT_BEFORE_S:
                self._texts.append(event)
            if self.state == "explaining" and is_reason(event):
                self._finish(Rejected(self._result, self._reason()))
            return
        if self.state != "waiting" or event.command != self.command:
            return
        if event.result == MAV_RESULT_IN_PROGRESS:
            self._deadline = min(self._hard_deadline, now + max(self.per_try, IN_PROGRESS_EXTENSION_S))
        elif event.result == MAV_RESULT_ACCEPTED:
            self._finish(Accepted())
        else:
            self._result = event.result
            self.state = "explaining"
            self._deadline = now + TEXT_GRACE_S
            if any(is_reason(t) for t in self._texts):
                self._finish(Rejected(self._result, self._reason()))

    def tick(self, now: float) -> list[Any]:
        """Act on the deadlines due at ``now``; return the messages to send (a retry)."""
        if self.outcome is not None or now < self._deadline:
            return []
        if self.state == "explaining":
            self._finish(Rejected(self._result, self._reason()))
            return []
        self.attempt += 1
        if self.attempt >= self.tries:
            self._finish(TimedOut(self.tries, self.per_try))
            return []
        self._deadline = now + self.per_try
        self._hard_deadline = now + self.in_progress_timeout
        return [self._message()]

    def _reason(self) -> str:
        """The texts that explain the refusal (warnings and worse, the autopilots' own
        refusal openings); none of those: every text heard, as it was."""
        reasons = [t.text for t in self._texts if is_reason(t)]
        return "; ".join(reasons or [t.text for t in self._texts])

    def _finish(self, outcome: Outcome) -> None:
        self.outcome = outcome
        self.state = "done"

    def error(self, autopilot: str) -> CommandRejected | CommandTimeout | None:
        """The error the outcome means for the caller (None when accepted or not done)."""
        name = command_name(self.command)
        out = self.outcome
        if isinstance(out, Rejected):
            result = MAV_RESULT_NAMES.get(out.result, str(out.result))
            return CommandRejected(
                f"{name} rejected by {autopilot}: {result}" + (f" ({out.text})" if out.text else ""),
                command=self.command,
                result=out.result,
                text=out.text,
            )
        if isinstance(out, TimedOut):
            return CommandTimeout(
                f"{name}: no COMMAND_ACK from {autopilot} after {out.tries} tries of {out.per_try:g} s"
            )
        return None
