"""Reading a flight log back: one agent's rotated ``.tlog`` files as one capture.

Theory of operation
-------------------
A flight log (:mod:`radios.rotating`) is a folder of ``PREFIX-STAMP-NNNN.tlog`` files
(the radio's traffic) and ``PREFIX-STAMP-NNNN.fc.tlog`` files (the flight
controller's), possibly of several agents and several starts.
:func:`flight_log_files` picks one prefix's files of one source, regular files only
(a FIFO named like a log would block the reader for ever), in the order their names
give: time, then counter. :class:`FlightLogReader` yields their records in that
order as one stream. A power cut leaves at most the last record of a file cut short
(:func:`torn_tail` tells that from damage by the bytes left: fewer than one whole
record); the reader skips it, notes it in ``torn`` and goes on with the next file.
Any other damage ends the reading with :class:`~radios.errors.CaptureDamagedError`,
after every good record before it, as :func:`radios.tlog.read_tlog` does.
"""

from __future__ import annotations

import os
from collections.abc import Generator, Iterator

from radios.errors import CaptureDamagedError, ConfigError
from radios.mavlink import STX_V1, STX_V2, frame_length
from radios.rotating import FC, NAME, RADIO, SOURCES, SUFFIX
from radios.tlog import TIMESTAMP_LEN, TlogRecord, read_tlog


def flight_log_files(directory: str, *, prefix: str | None = None, source: str = RADIO) -> list[str]:
    """The paths of ``source``'s files in ``directory``, in time order, for ``prefix``
    (an agent's name; None: the only prefix there). Only regular files count.

    Raises:
        ConfigError: an unknown source, a folder that cannot be listed, several
            prefixes and none chosen, or no file of that prefix and source.
    """
    if source not in SUFFIX:
        raise ConfigError(f"unknown flight log source {source!r}: {', '.join(SOURCES)}")
    try:
        names = os.listdir(directory)
    except OSError as exc:
        raise ConfigError(f"cannot list {directory}: {exc.strerror or exc}") from None
    found: dict[str, list[tuple[str, int, str]]] = {}
    for n in names:
        m = NAME.match(n)
        # only regular files: a FIFO or a device named like a log would block or never end
        if m is not None and bool(m["fc"]) == (source == FC) and os.path.isfile(os.path.join(directory, n)):
            found.setdefault(m["prefix"], []).append((m["stamp"], int(m["seq"]), n))
    if prefix is None:
        if len(found) > 1:
            raise ConfigError(f"{directory} holds the flight logs of {', '.join(sorted(found))}: choose one")
        prefix = next(iter(found), None)
    if prefix is None or prefix not in found:
        who = f" of {prefix}" if prefix else ""
        raise ConfigError(f"{directory}: no {source} flight log{who} (*{SUFFIX[source]})")
    return [os.path.join(directory, n) for _, _, n in sorted(found[prefix])]


def torn_tail(path: str, offset: int) -> bool:
    """Whether the bytes of ``path`` from ``offset`` to its end are one record cut
    short (what a power cut leaves), rather than damage."""
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            rest = f.read(TIMESTAMP_LEN + 300)
    except OSError:
        return False
    if len(rest) <= TIMESTAMP_LEN:
        return True
    if len(rest) < TIMESTAMP_LEN + 3:
        return rest[TIMESTAMP_LEN] in (STX_V1, STX_V2)
    total = frame_length(rest[TIMESTAMP_LEN:])
    return total is not None and len(rest) < TIMESTAMP_LEN + total


class FlightLogReader:
    """The records of several ``.tlog`` files as one capture (see
    :func:`read_flight_log`); ``torn`` lists ``(path, offset)`` of the torn records
    skipped, ``records`` counts the records read, ``path`` names the set."""

    def __init__(self, paths: list[str], name: str) -> None:
        self.paths = paths
        self.path = name
        self.torn: list[tuple[str, int]] = []
        self.unknown: dict[int, int] = {}  # message id -> frames skipped (see TlogReader)
        self.records = 0
        self._it = self._records()

    def __iter__(self) -> Iterator[TlogRecord]:
        return self

    def __next__(self) -> TlogRecord:
        rec = next(self._it)
        self.records += 1
        return rec

    def _records(self) -> Generator[TlogRecord, None, None]:
        for path in self.paths:
            reader = read_tlog(path)
            try:
                yield from reader
            except CaptureDamagedError as exc:
                if not torn_tail(path, exc.offset):
                    raise
                self.torn.append((path, exc.offset))
            finally:
                reader.close()
                for msgid, n in reader.unknown.items():
                    self.unknown[msgid] = self.unknown.get(msgid, 0) + n

    def close(self) -> None:
        self._it.close()


def read_flight_log(directory: str, *, prefix: str | None = None, source: str = RADIO) -> FlightLogReader:
    """Read one agent's rotated set (:func:`flight_log_files`) as one capture.

    Raises:
        ConfigError: as :func:`flight_log_files`.

    Iterating raises:
        CaptureError: a file of the set cannot be opened.
        CaptureDamagedError: damage other than a torn last record (after every good
            record before it).
    """
    paths = flight_log_files(directory, prefix=prefix, source=source)
    return FlightLogReader(paths, directory)


__all__ = ["FlightLogReader", "flight_log_files", "read_flight_log", "torn_tail"]
