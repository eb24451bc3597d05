"""Errors of the radio layer.

Every error raised on purpose by `radios` derives from :class:`RadioError`.
The classes say who is at fault:

* :class:`LinkOpenError`, :class:`ConfigError`: the caller's input (a URL, a path,
  a parameter value) is wrong; :class:`DeviceMismatchError`: the path names another
  device than the one the link opened.
* :class:`ATError`: the radio answered, but not as the protocol says.
* :class:`CaptureDamagedError`: a capture file is truncated or corrupted.
* Timeouts also derive from the built-in :class:`TimeoutError`.
"""

from __future__ import annotations


class RadioError(Exception):
    """Base of every error the radio layer raises on purpose."""


class LinkError(RadioError):
    """A link could not do what was asked."""


class LinkOpenError(LinkError):
    """A link URL is malformed, names an unknown scheme, or its device is missing."""


class DeviceMismatchError(LinkOpenError):
    """Another device is at a link's path than the one it opened first (a reassigned
    ``/dev/ttyUSB0`` or pty): it is refused unopened. ``expected`` and ``found`` are
    their :class:`radios.device_id.DeviceIdentity`."""

    def __init__(self, message: str, *, expected: object = None, found: object = None) -> None:
        super().__init__(message)
        self.expected = expected
        self.found = found


class LinkClosedError(LinkError):
    """The link was used after close(), or its device went away."""


class LinkTimeoutError(LinkError, TimeoutError):
    """A blocking link operation did not complete in time."""


class FrameError(RadioError, ValueError):
    """The caller tried to send something that is not a valid MAVLink 2 frame."""


class ConfigError(RadioError, ValueError):
    """A configuration value (parameter name, value, option) is invalid."""


class ATError(RadioError):
    """The radio's AT command interface answered ERROR or something unexpected."""


class ATTimeoutError(ATError, TimeoutError):
    """The radio did not answer an AT command (or +++) in time."""


class CaptureError(RadioError):
    """A capture (.tlog) file cannot be opened or written."""


class CaptureDamagedError(CaptureError):
    """A capture file is truncated or corrupted.

    ``offset`` is the byte offset of the first damaged record and ``records`` the
    number of whole records read before it.
    """

    def __init__(self, message: str, *, offset: int, records: int) -> None:
        super().__init__(message)
        self.offset = offset
        self.records = records
