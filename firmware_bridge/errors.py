"""Errors of the flight-controller bridge.

Every error raised on purpose by ``firmware_bridge`` derives from
:class:`BridgeError`. :class:`ConnectError` and :class:`SetpointError` are the
caller's input; :class:`CommandRejected` is the autopilot's answer (it carries the
MAV_RESULT code and the autopilot's STATUSTEXT); timeouts also derive from
:class:`TimeoutError`.
"""

from __future__ import annotations


class BridgeError(Exception):
    """Base of every error the flight-controller bridge raises on purpose."""


class ConnectError(BridgeError):
    """A connection string is malformed, or its port/device cannot be opened."""


class HeartbeatTimeout(ConnectError, TimeoutError):
    """No autopilot heartbeat arrived in time."""


class CommandRejected(BridgeError):
    """The autopilot answered a command with a result other than ACCEPTED.

    ``result`` is the MAV_RESULT code, ``text`` the autopilot's STATUSTEXT if any.
    """

    def __init__(self, message: str, *, command: int, result: int, text: str = "") -> None:
        super().__init__(message)
        self.command = command
        self.result = result
        self.text = text


class FlightInterrupted(BridgeError):
    """The vehicle stopped doing what it was told while the driver waited for it: it
    disarmed, or its autopilot left the commanded mode by itself (a failsafe, a
    landing, the pilot's RC). ``state`` is the vehicle's state then."""

    def __init__(self, message: str, *, state: object = None) -> None:
        super().__init__(message)
        self.state = state


class CommandTimeout(BridgeError, TimeoutError):
    """The autopilot never acknowledged a command, after all retries."""


class SetpointError(BridgeError, ValueError):
    """A setpoint is NaN, infinite or out of range: refused before it reaches the vehicle."""
