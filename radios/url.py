"""Link URLs: one grammar for the strings that name a channel.

Theory of operation
-------------------
Pure: a string goes in, a value comes out, and anything malformed raises
:class:`~radios.errors.LinkOpenError` with a one-line message naming the string.
Nothing here opens, stats or imports a backend; :mod:`radios.link` looks the
parsed scheme up in its registry.

A radio link URL is ``[SCHEME:[//]]TARGET[?NAME=VALUE&...]`` (:func:`parse_link_url`):

==========================================  ===========  ==========================
form                                        scheme       target
==========================================  ===========  ==========================
``/dev/ttyUSB0?baud=57600``, ``COM3``       ``serial``   the device path
``serial:/dev/x``, ``serial:///dev/x``      ``serial``   ``/dev/x``
``loop://``, ``socket://host:port``...      ``loop``...  the whole pyserial URL
``tlog:flight.tlog?speed=2``, ``x.tlog``    ``tlog``     the capture file
``virtual://NAME?loss=0.1``                 ``virtual``  the bus name
==========================================  ===========  ==========================

An explicit scheme wins over the ``.tlog`` ending (``serial:/dev/x.tlog`` is a
serial device); a bare path ending in ``.tlog`` is a capture. A first path segment
with a colon that is no scheme of the list above (``foo:bar``, ``foo://x``) is
parsed as scheme ``foo``, which the registry then refuses by name. Options are
strings; :class:`Options` reads them typed and refuses leftovers.

The flight-controller connection strings (``serial:/dev/ttyAMA0:921600``,
``udp:``/``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``) have their
own small grammar, :func:`parse_endpoint`, in the same terms: a scheme, then a
device and baud rate or a host and port; it also takes the serial form of a link
URL (``/dev/ttyAMA0?baud=921600``), so one string names a serial port for both.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Literal
from urllib.parse import parse_qsl

from radios.errors import LinkOpenError

#: URL schemes handled by pyserial's ``serial_for_url`` (the target keeps its scheme).
PYSERIAL_SCHEMES = ("loop", "socket", "rfc2217", "spy", "alt", "hwgrep")

_SCHEME = re.compile(r"([A-Za-z][A-Za-z0-9+.\-]*):")


@dataclass(frozen=True)
class LinkURL:
    """A parsed link URL: ``url`` as given, ``scheme`` (lower case), ``target`` (what
    the scheme's backend opens) and ``options`` (the query, as strings)."""

    url: str
    scheme: str
    target: str
    options: dict[str, str] = field(default_factory=dict, hash=False)


def split_query(url: str) -> tuple[str, dict[str, str]]:
    """``("PATH", {name: value})`` for ``PATH?name=value&...`` (the last of repeated
    names wins; blank values are kept)."""
    if "?" in url:
        path, query = url.split("?", 1)
        return path, dict(parse_qsl(query, keep_blank_values=True))
    return url, {}


def parse_link_url(url: str) -> LinkURL:
    """Parse a radio link URL (see the module docstring for the forms).

    Raises:
        LinkOpenError: ``url`` is empty, not a string, or holds a NUL character (no
            path can).
    """
    if not isinstance(url, str) or not url:
        raise LinkOpenError("empty link URL")
    if "\x00" in url:
        raise LinkOpenError(f"{url!r}: a link URL cannot contain a NUL character")
    path, options = split_query(url)
    m = _SCHEME.match(path)
    if m is not None and not m.group(1).upper().startswith("COM"):
        scheme, rest = m.group(1).lower(), path[m.end() :]
        if scheme in PYSERIAL_SCHEMES:
            return LinkURL(url, scheme, path, options)  # pyserial parses its own URL
        return LinkURL(url, scheme, rest.removeprefix("//"), options)
    head = path.split("/", 1)[0]
    if ":" in head and not head.upper().startswith("COM"):
        return LinkURL(url, head.split(":", 1)[0], path, options)  # "1:x": no scheme we know
    return LinkURL(url, "tlog" if path.endswith(".tlog") else "serial", path, options)


class Options:
    """Typed reading of a link URL's options; :meth:`finish` refuses what is left.

    Raises (each method):
        LinkOpenError: the value does not parse, or (:meth:`finish`) an option
            nobody read.
    """

    def __init__(self, url: LinkURL) -> None:
        self.url = url.url
        self._left = dict(url.options)

    def integer(self, name: str, default: int) -> int:
        if name not in self._left:
            return default
        try:
            return int(self._left.pop(name))
        except ValueError:
            raise LinkOpenError(f"{self.url}: {name} must be an integer") from None

    def number(self, name: str, default: float) -> float:
        if name not in self._left:
            return default
        try:
            return float(self._left.pop(name))
        except ValueError:
            raise LinkOpenError(f"{self.url}: {name} must be a number") from None

    def finish(self, known: tuple[str, ...] | None = None) -> None:
        """Refuse the options nobody read (``known`` is listed in the message)."""
        if self._left:
            hint = f" (known: {', '.join(known)})" if known else ""
            raise LinkOpenError(f"{self.url}: unknown option(s) {', '.join(sorted(self._left))}{hint}")


# -- flight-controller connection strings ---------------------------------------------

FC_DEFAULT_BAUD = 57600


@dataclass(frozen=True)
class Endpoint:
    """A parsed flight-controller connection string: ``scheme`` is serial, udpin,
    udpout or tcp."""

    scheme: Literal["serial", "udpin", "udpout", "tcp"]
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.scheme == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.scheme}:{self.host}:{self.port}"


def parse_host_port(scheme: str, rest: str, url: str) -> tuple[str, int]:
    """``(host, port)`` of ``[//]HOST:PORT`` (``[v6]`` brackets dropped, the host may
    be empty).

    Raises:
        LinkOpenError: no port, a port that is no number or out of 1-65535.
    """
    rest = rest.removeprefix("//")
    host, sep, port_s = rest.rpartition(":")
    if not sep:
        raise LinkOpenError(f"{url!r}: expected {scheme}:HOST:PORT")
    host = host.strip("[]")
    try:
        port = int(port_s)
    except ValueError:
        raise LinkOpenError(f"{url!r}: port {port_s!r} is not a number") from None
    if not 0 < port < 65536:
        raise LinkOpenError(f"{url!r}: port {port} out of range 1-65535")
    return host, port


def _serial_endpoint(rest: str, url: str, default_baud: int) -> Endpoint:
    device, colon, baud_s = rest.rpartition(":")
    if not colon:
        device, baud = rest, default_baud
    else:
        try:
            baud = int(baud_s)
        except ValueError:
            raise LinkOpenError(f"{url!r}: baud rate {baud_s!r} is not a number") from None
        if baud <= 0:
            raise LinkOpenError(f"{url!r}: baud rate must be positive")
    if not device:
        raise LinkOpenError(f"{url!r}: no serial device")
    return Endpoint("serial", device=device, baud=baud)


def _serial_link_endpoint(url: str, default_baud: int) -> Endpoint:
    link = parse_link_url(url)
    if link.scheme != "serial":
        raise LinkOpenError(f"{url!r}: a flight controller is not reached by {link.scheme!r}")
    opts = Options(link)
    baud = opts.integer("baud", default_baud)
    opts.finish(known=("baud",))
    if baud <= 0:
        raise LinkOpenError(f"{url!r}: baud rate must be positive")
    if not link.target:
        raise LinkOpenError(f"{url!r}: no serial device")
    return Endpoint("serial", device=link.target, baud=baud)


def parse_endpoint(url: str, *, default_baud: int = FC_DEFAULT_BAUD) -> Endpoint:
    """Parse ``serial:/dev/ttyAMA0:921600``, ``udp:``/``udpin:HOST:PORT`` (listen),
    ``udpout:HOST:PORT`` or ``tcp:HOST:PORT``. A bare ``/dev/...`` path is a serial
    port (``default_baud`` unless ``:BAUD`` follows); ``udp://:14540`` (MAVSDK style)
    listens on every address. The radio links' serial form is understood too:
    ``/dev/ttyAMA0?baud=921600`` or ``serial:/dev/ttyAMA0?baud=921600``.

    Raises:
        LinkOpenError: malformed string or unknown scheme (nothing is opened here).
    """
    if not isinstance(url, str) or not url.strip():
        raise LinkOpenError(f"empty connection string {url!r}")
    url = url.strip()
    if "?" in url:  # a radio link URL's serial form: /dev/x?baud=N, serial:/dev/x?baud=N
        return _serial_link_endpoint(url, default_baud)
    if url.startswith("/"):
        url = "serial:" + url
    scheme, sep, rest = url.partition(":")
    scheme = scheme.lower()
    if not sep or not rest:
        raise LinkOpenError(
            f"{url!r}: expected SCHEME:..., e.g. udpin:127.0.0.1:14540, "
            "tcp:127.0.0.1:5760 or serial:/dev/ttyAMA0:921600"
        )
    if scheme == "serial":
        return _serial_endpoint(rest, url, default_baud)
    if scheme in ("udp", "udpin"):
        host, port = parse_host_port(scheme, rest, url)
        return Endpoint("udpin", host=host or "0.0.0.0", port=port)
    if scheme in ("udpout", "tcp"):
        host, port = parse_host_port(scheme, rest, url)
        if not host:
            raise LinkOpenError(f"{url!r}: {scheme} needs a host")
        return Endpoint("tcp" if scheme == "tcp" else "udpout", host=host, port=port)
    raise LinkOpenError(f"{url!r}: unknown scheme {scheme!r} (serial, udp, udpin, udpout, tcp)")


__all__ = [
    "FC_DEFAULT_BAUD",
    "PYSERIAL_SCHEMES",
    "Endpoint",
    "LinkURL",
    "Options",
    "parse_endpoint",
    "parse_host_port",
    "parse_link_url",
    "split_query",
]
