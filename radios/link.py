"""Links opened by URL: the registry of backends and the one factory.

Theory of operation
-------------------
:func:`open_link` parses a URL with the one grammar (:mod:`radios.url`), looks its
scheme up in :data:`BACKENDS` (python-can's ``BACKENDS`` map), imports that
backend's module only then, and calls its factory with the parsed URL and the
caller's keyword options. The factory checks its own options and opens the link;
``capture=PATH`` then wraps whatever it opened in a
:class:`~radios.capture.CaptureLink`, so capturing works on every backend.

========================================  ========================================
``/dev/ttyUSB0?baud=57600``               serial device (also ``serial:/dev/...``)
``DIR/radio0``                            an emulator pty: just a serial device
``loop://``, ``socket://host:port``       pyserial URL handlers
``tlog:flight.tlog?speed=1`` or ``*.tlog`` replay a capture (receive only)
``virtual://NAME?loss=P&seed=N``           an in-process bus (:mod:`radios.virtual`)
========================================  ========================================

Imports go one way: this module imports the grammar, the base class and the
capture wrapper; the backends import the base class (:mod:`radios.linkbase`) and
the grammar, never this module. The registry is a read-only mapping: tests add
backends by writing a :class:`~radios.linkbase.Link` subclass, not by changing
what every other test opens.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from types import MappingProxyType
from typing import Any

from radios.capture import CaptureLink, CaptureSink
from radios.errors import FrameError, LinkOpenError
from radios.linkbase import Link, LinkStats
from radios.url import PYSERIAL_SCHEMES, LinkURL, parse_link_url

_SERIAL = "radios.seriallink:open_serial_url"

#: scheme -> ``"module:factory"``; the factory is called as ``factory(LinkURL, **options)``.
BACKENDS: MappingProxyType[str, str] = MappingProxyType(
    {
        "serial": _SERIAL,
        "tlog": "radios.replay:open_tlog_url",
        "virtual": "radios.virtual:open_virtual",
        **{scheme: _SERIAL for scheme in PYSERIAL_SCHEMES},
    }
)

#: The schemes as users write them, for messages and help.
SCHEMES = ("serial:", "tlog:", "virtual://", *(f"{s}://" for s in PYSERIAL_SCHEMES))


def backend(scheme: str, url: str = "") -> Callable[..., Link]:
    """The factory of ``scheme``, its module imported now.

    Raises:
        LinkOpenError: no backend has that scheme.
    """
    spec = BACKENDS.get(scheme)
    if spec is None:
        where = f"{url}: " if url else ""
        raise LinkOpenError(f"{where}unknown link scheme {scheme!r} (known: {', '.join(SCHEMES)})")
    module, _, attr = spec.partition(":")
    factory: Callable[..., Link] = getattr(importlib.import_module(module), attr)
    return factory


def open_link(
    url: str, *, capture: str | os.PathLike[str] | CaptureSink | None = None, **options: Any
) -> Link:
    """Open a link by URL (see the module docstring for the forms).

    ``capture`` wraps the link so every frame sent and received is also written to
    that ``.tlog`` (or to that :class:`~radios.capture.CaptureSink`). Extra keyword
    ``options`` go to the backend (the replay backend takes ``clock`` and ``sleep``;
    the others take none).

    Raises:
        LinkOpenError: unknown scheme, malformed URL or option, missing device.
        CaptureError: the capture file cannot be created (the link is closed again).
    """
    parsed: LinkURL = parse_link_url(url)
    link = backend(parsed.scheme, url)(parsed, **options)
    if capture is not None:
        try:
            link = CaptureLink(link, capture)
        except BaseException:
            link.close()
            raise
    return link


__all__ = [
    "BACKENDS",
    "SCHEMES",
    "FrameError",
    "Link",
    "LinkStats",
    "backend",
    "open_link",
]
