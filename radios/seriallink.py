"""The serial backend: a radio, an emulator pty, or a pyserial URL handler.

Theory of operation
-------------------
:class:`SerialLink` implements the :class:`~radios.linkbase.Link` hooks on a
pyserial port. Reads wait in ``select`` on the port's file descriptor when it has
one (a device, a pty) and fall back to pyserial's own timeout otherwise
(``loop://``, ``socket://``); a read or write error means the device went away
(``LinkClosedError``), a write that cannot finish in ``write_timeout`` is a
``LinkTimeoutError`` (the frame counts as a drop). The link can be released (the
port closed, the link kept) and reopened at the same URL with the same options.

**A device is the device it was** (:mod:`radios.device_id`): a device path's identity
(USB ids, serial number and port; the emulator's radio; a pty's node) is read when
the link opens it (:attr:`SerialLink.identity`, read by :mod:`radios.device_probe`
without opening it) and read again before every reopen; another device at the same
path is refused with one line naming both (:class:`~radios.errors.DeviceMismatchError`)
before it is opened, so it never gets a byte. pyserial URLs have no identity.

:func:`open_serial_url` is the backend factory :mod:`radios.link` calls for the
``serial`` scheme, bare device paths and pyserial's schemes (options ``baud``,
``rtscts``, ``write_timeout``); :func:`open_serial` takes the URL as a string.
"""

from __future__ import annotations

import os
import select
from typing import Any

from radios.device_id import DeviceIdentity, mismatch, refusal
from radios.device_probe import confirm, identify
from radios.errors import DeviceMismatchError, LinkClosedError, LinkOpenError, LinkTimeoutError
from radios.linkbase import Link
from radios.mavlink import FrameParser
from radios.url import PYSERIAL_SCHEMES, LinkURL, Options, parse_link_url

DEFAULT_BAUD = 57600


class SerialLink(Link):
    """A serial device (real radio, emulator pty) or a pyserial URL handler."""

    can_reopen = True

    def __init__(self, url: str, port: Any, identity: DeviceIdentity | None = None) -> None:
        super().__init__(url)
        self.port = port
        self._identity = identity
        self._gone = False  # the device went away; reopen() may bring it back
        self._fd = self._fileno(port)

    @staticmethod
    def _fileno(port: Any) -> int | None:
        try:
            return int(port.fileno())
        except Exception:
            return None

    @property
    def identity(self) -> DeviceIdentity | None:
        """The device this link opened first (None for a pyserial URL)."""
        return self._identity

    def check_device(self) -> None:
        """See :meth:`Link.check_device`."""
        if self._identity is not None:
            _check(parse_link_url(self.url).target, self._identity)

    def reopen(self) -> None:
        """See :meth:`Link.reopen`: the old port is closed first, then the device at the
        path is identified and, if it is the device first opened, opened again with the
        same options.

        Raises:
            DeviceMismatchError: another device is at the path (it is not opened).
        """
        with self._send_lock, self._recv_lock:
            if self._closed:
                raise LinkClosedError(f"{self.url} is closed")
            if not self._gone:
                self._gone = True
                self._close()
            fresh = open_serial_url(parse_link_url(self.url), expected=self._identity)
            self.port, self._fd = fresh.port, fresh._fd  # noqa: SLF001 (the same class's)
            self._parser = FrameParser(stats=self._parser.stats)
            self._pending.clear()
            self._gone = False

    def release(self) -> None:
        """See :meth:`Link.release`."""
        with self._send_lock, self._recv_lock:
            if not self._closed and not self._gone:
                self._gone = True
                self._close()

    def _read(self, timeout: float) -> bytes:
        if self._closed:
            raise LinkClosedError(f"{self.url} is closed")
        if self._gone:
            raise LinkClosedError(f"{self.url}: device gone")
        try:
            if self._fd is not None:
                r, _, _ = select.select([self._fd], [], [], timeout)
                if not r:
                    return b""
                data = os.read(self._fd, 4096)
                if not data:
                    raise LinkClosedError(f"{self.url}: device closed")
                return data
            self.port.timeout = timeout
            n = max(1, self.port.in_waiting)
            return bytes(self.port.read(n))
        except OSError as exc:
            # EIO on a pty whose master went away, EBADF after close()
            raise LinkClosedError(f"{self.url}: {exc.strerror or exc}") from exc
        except ValueError as exc:  # select on a closed fd
            raise LinkClosedError(f"{self.url} is closed") from exc

    def _write(self, data: bytes) -> None:
        import serial

        if self._gone:
            raise LinkClosedError(f"{self.url}: device gone")
        try:
            n = self.port.write(data)
        except serial.SerialTimeoutException as exc:
            raise LinkTimeoutError(f"{self.url}: write timed out (nobody reading?)") from exc
        except (OSError, serial.SerialException) as exc:
            raise LinkClosedError(f"{self.url}: {exc}") from exc
        if n is not None and n != len(data):
            raise LinkTimeoutError(f"{self.url}: only {n} of {len(data)} bytes written")

    def _close(self) -> None:
        try:
            self.port.close()
        except Exception:  # closing a device that already vanished
            pass


def open_serial(url: str) -> SerialLink:
    """Open a serial device or pyserial URL given as a string, see
    :func:`open_serial_url`."""
    return open_serial_url(parse_link_url(url))


def _serial_options(url: LinkURL) -> tuple[int, bool, float]:
    opts = Options(url)
    baud = opts.integer("baud", DEFAULT_BAUD)
    rtscts = bool(opts.integer("rtscts", 0))
    write_timeout = opts.number("write_timeout", 2.0)
    opts.finish()
    if baud <= 0:
        raise LinkOpenError(f"{url.url}: baud must be positive")
    return baud, rtscts, write_timeout


def _check(target: str, expected: DeviceIdentity) -> DeviceIdentity:
    """The identity of the device at ``target`` now, if it is ``expected``'s device.

    Raises:
        DeviceMismatchError: another device (the one line names both).
        LinkOpenError: none, or it cannot be identified.
    """
    found = identify(target)
    why = mismatch(expected, found)
    if why is not None:
        raise DeviceMismatchError(refusal(target, expected, found, why), expected=expected, found=found)
    return found


def open_serial_url(url: LinkURL, *, expected: DeviceIdentity | None = None, **options: Any) -> SerialLink:
    """Open the serial device or pyserial URL ``url`` names (the backend factory).
    With ``expected`` (a reopen), only that device: another is refused unopened.

    Raises:
        LinkOpenError: a malformed or unknown option, keyword ``options`` (a serial
            link takes none), no device path, a missing device, or pyserial cannot
            open it.
        DeviceMismatchError: the device at the path is not ``expected``'s.
    """
    import serial

    if options:
        raise LinkOpenError(f"unexpected options for a serial link: {', '.join(options)}")
    baud, rtscts, write_timeout = _serial_options(url)
    target = url.target
    is_url = url.scheme in PYSERIAL_SCHEMES
    if is_url and not target.lower().startswith(f"{url.scheme}://"):
        raise LinkOpenError(f"{url.url}: a pyserial URL is written {url.scheme}://...")
    identity = None
    if not is_url:
        if not target:
            raise LinkOpenError(f"{url.url}: no device path")
        identity = identify(target) if expected is None else _check(target, expected)
    try:
        if is_url:
            port = serial.serial_for_url(
                target, baudrate=baud, rtscts=rtscts, write_timeout=write_timeout, timeout=0
            )
        else:
            port = serial.Serial(
                target, baudrate=baud, rtscts=rtscts, write_timeout=write_timeout, timeout=0, exclusive=False
            )
    except (serial.SerialException, OSError, ValueError) as exc:
        raise LinkOpenError(f"cannot open {target}: {exc}") from exc
    if identity is not None:
        try:
            confirm(SerialLink._fileno(port), identity, target)  # noqa: SLF001 (the same class's)
        except (LinkOpenError, OSError):
            port.close()
            raise LinkOpenError(f"{target}: the device changed while it was being opened") from None
        if expected is not None:
            identity = expected  # what a later reopen compares with stays the first device
    return SerialLink(url.url, port, identity)


__all__ = ["DEFAULT_BAUD", "SerialLink", "open_serial", "open_serial_url"]
