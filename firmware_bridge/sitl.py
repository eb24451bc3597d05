"""Real autopilots on this machine: ArduCopter and PX4 SITL started, found and stopped.

Theory of operation
-------------------
A SITL folder (``$SITL_DIR``; else ``../shared/sitl`` beside a checkout, when it
exists) holds two start scripts, ``run-arducopter`` and ``run-px4``, each running one
autopilot in the foreground (the PID started is the autopilot's) with its own flight
code and built-in physics: ``run-arducopter WORKDIR --instance N [--sysid S]
[--home LAT,LON,ALT,HDG] [--speedup F]`` serves MAVLink on TCP 127.0.0.1:5760+10N;
``run-px4 WORKDIR --instance N [--home LAT,LON,ALT] [--speed F]`` sends it to UDP
127.0.0.1:14540+N (the driver listens there: ``udpin:``). The docs' "Real
autopilots" section says how to build both from the upstream sources.

:func:`start` picks an instance number nobody on this machine holds (a lock file per
kind and number under the temporary folder, held as long as the autopilot runs, and
its ports checked free), gives the autopilot a working folder of its own (ArduPilot's
eeprom.bin, PX4's parameters and flight logs: a folder kept between two starts is a
warm boot) and returns a :class:`Sitl`: its connection string, system id, process
and log file. :meth:`Sitl.stop` sends SIGTERM, waits, then kills; a context manager.

Nothing here judges the autopilot: tests and benches do (``tests/test_sitl_*.py``,
``swarm bench conformance --real``).
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

from firmware_bridge.errors import BridgeError

__all__ = ["KINDS", "Sitl", "SitlError", "find_sitl", "script", "start"]

Kind = Literal["ardupilot", "px4"]
KINDS: tuple[Kind, ...] = ("ardupilot", "px4")
SCRIPTS = {"ardupilot": "run-arducopter", "px4": "run-px4"}
#: instance numbers tried, per kind: the low ones are left to the user's own autopilots and
#: simulators on their default ports (ArduPilot TCP 5760, 5770, 5790: instances 0, 1 and 3;
#: PX4 UDP 14540-14542: `swarm sim --vehicles 3`); PX4's 14540+N stays below its GCS port 14550
INSTANCES = {"ardupilot": range(4, 60), "px4": range(3, 10)}
STOP_S = 10.0  # SIGTERM, then SIGKILL after this long
LOCK_DIR = Path(tempfile.gettempdir()) / "swarm-sitl-locks"


class SitlError(BridgeError):
    """No SITL folder, no free instance, an autopilot that would not start."""


def find_sitl(environ: dict[str, str] | None = None, checkout: Path | None = None) -> Path | None:
    """The SITL folder: ``$SITL_DIR`` if set (even when it is wrong: :func:`script`
    says so), else ``../shared/sitl`` beside the checkout when it holds both scripts,
    else None."""
    env = os.environ if environ is None else environ
    given = env.get("SITL_DIR", "").strip()
    if given:
        return Path(given).expanduser()
    root = checkout if checkout is not None else Path(__file__).resolve().parent.parent
    beside = root.parent / "shared" / "sitl"
    if all((beside / s).is_file() for s in SCRIPTS.values()):
        return beside
    return None


def script(kind: Kind, sitl_dir: Path | None = None) -> Path:
    """The start script of ``kind`` in the SITL folder.

    Raises:
        SitlError: no folder, or the script is not there or not executable.
    """
    d = sitl_dir if sitl_dir is not None else find_sitl()
    if d is None:
        raise SitlError("no real autopilots: set SITL_DIR to a folder with run-arducopter and run-px4")
    path = d / SCRIPTS[kind]
    if not path.is_file() or not os.access(path, os.X_OK):
        raise SitlError(f"{path}: no {SCRIPTS[kind]} there (SITL_DIR={d})")
    return path


def ports(kind: Kind, instance: int) -> list[tuple[int, int]]:
    """The (socket type, port) pairs an instance binds or is reached on."""
    if kind == "ardupilot":
        base = 5760 + 10 * instance
        return [(socket.SOCK_STREAM, base), (socket.SOCK_STREAM, base + 2), (socket.SOCK_STREAM, base + 3)]
    return [
        (socket.SOCK_DGRAM, 14540 + instance),
        (socket.SOCK_DGRAM, 14580 + instance),
        (socket.SOCK_DGRAM, 18570 + instance),
    ]


def _port_free(kind: int, port: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _claim(kind: Kind, wanted: int | None) -> tuple[int, IO[str]]:
    """An instance number of ``kind`` and its lock file (held open: the claim)."""
    LOCK_DIR.mkdir(mode=0o1777, parents=True, exist_ok=True)
    with contextlib.suppress(OSError):
        os.chmod(LOCK_DIR, 0o1777)  # shared by every user's tests
    numbers = [wanted] if wanted is not None else list(INSTANCES[kind])
    for n in numbers:
        lock = open(LOCK_DIR / f"{kind}-{n}.lock", "a+")  # noqa: SIM115 - held while it runs
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            continue
        if all(_port_free(t, p) for t, p in ports(kind, n)) and not (
            kind == "px4" and Path(tempfile.gettempdir(), f"px4-sock-{n}").exists() and _px4_alive(n)
        ):
            return n, lock
        lock.close()
    what = f"instance {wanted}" if wanted is not None else "a free instance"
    raise SitlError(f"{kind} SITL: {what} is taken (its ports are in use)")


def _px4_alive(n: int) -> bool:
    """A PX4 of instance ``n`` still runs (its lock file is held by a live process)."""
    lock = Path(tempfile.gettempdir(), f"px4_lock-{n}")
    if not lock.exists():
        return False
    try:
        with open(lock) as f:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return False
    except OSError:
        return True


def _px4_aliases(bin_dir: Path, path_dir: Path) -> None:
    """PX4's start script runs its modules through ``px4-<module>`` aliases, links to
    the ``px4`` binary. A copy that lost its links (stored as files holding the word
    ``px4``, as git stores a link) cannot boot: every ``px4-param`` fails, no airframe
    starts and no heartbeat ever comes. Such aliases are linked again in the working
    folder's ``path`` (first on the script's PATH)."""
    binary = bin_dir / "px4"
    if not binary.is_file():
        return
    path_dir.mkdir(parents=True, exist_ok=True)
    for alias in bin_dir.glob("px4-*"):
        if alias.is_symlink() or alias.suffix == ".sh" or os.access(alias, os.X_OK):
            continue
        try:
            if alias.stat().st_size > 64 or alias.read_bytes().strip() != b"px4":
                continue
        except OSError:
            continue
        link = path_dir / alias.name
        if not link.is_symlink():
            with contextlib.suppress(FileExistsError):
                link.symlink_to(binary)


@dataclass
class Sitl:
    """One running autopilot (made by :func:`start`)."""

    kind: Kind
    instance: int
    sysid: int
    url: str
    workdir: Path
    log_path: Path
    proc: subprocess.Popen[bytes]
    speed: float = 1.0
    _lock: IO[str] | None = field(default=None, repr=False)
    _log: IO[bytes] | None = field(default=None, repr=False)

    @property
    def running(self) -> bool:
        return self.proc.poll() is None

    def log_tail(self, lines: int = 5) -> str:
        """The autopilot's last output lines (for a failure message)."""
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return " | ".join(ln.strip() for ln in text.splitlines()[-lines:] if ln.strip())

    def stop(self) -> int | None:
        """SIGTERM, wait up to :data:`STOP_S`, then SIGKILL. Returns the exit code."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGTERM)  # setsid: the autopilot leads its group
            try:
                self.proc.wait(STOP_S)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(STOP_S)
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._lock is not None:
            self._lock.close()  # the claim ends
            self._lock = None
        return self.proc.returncode

    def __enter__(self) -> Sitl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start(
    kind: Kind,
    workdir: Path,
    *,
    instance: int | None = None,
    home: tuple[float, float, float] | tuple[float, float, float, float] | None = None,
    speed: float = 1.0,
    sitl_dir: Path | None = None,
    sysid: int | None = None,
) -> Sitl:
    """Start one real autopilot of ``kind`` with its working folder ``workdir`` (made if
    needed; kept between starts for a warm boot). ``home`` is (lat, lon, alt AMSL[,
    heading]); ``speed`` runs its clock faster (ArduPilot ``--speedup``, PX4 ``--speed``);
    ``sysid`` (ArduCopter only: PX4's is its instance + 1) its MAVLink system id.

    Raises:
        SitlError: no SITL folder or script, bad arguments, no free instance, or the
            process ended at once.
    """
    if kind not in KINDS:
        raise SitlError(f"unknown autopilot {kind!r}: {' or '.join(KINDS)}")
    if not (isinstance(speed, int | float) and math.isfinite(speed) and 0.1 <= speed <= 20):
        raise SitlError(f"speed {speed!r}: a number of 0.1..20")
    if home is not None and not all(isinstance(v, int | float) and math.isfinite(v) for v in home):
        raise SitlError(f"home {home!r}: finite numbers")
    if sysid is not None and (kind != "ardupilot" or not (isinstance(sysid, int) and 1 <= sysid <= 250)):
        raise SitlError(f"sysid {sysid!r}: 1..250, ArduCopter only (PX4's is its instance + 1)")
    path = script(kind, sitl_dir)
    n, lock = _claim(kind, instance)
    try:
        workdir.mkdir(parents=True, exist_ok=True)
        if kind == "px4":
            _px4_aliases(path.parent / "px4" / "bin", workdir / "path")
        log_path = workdir / f"{kind}-{n}.log"
        args = [str(path), str(workdir), "--instance", str(n)]
        if home is not None:
            args += ["--home", ",".join(f"{v:.7f}".rstrip("0").rstrip(".") for v in home)]
        if speed != 1.0:
            args += ["--speedup" if kind == "ardupilot" else "--speed", f"{speed:g}"]
        if sysid is not None:
            args += ["--sysid", str(sysid)]
        log = open(log_path, "ab")  # noqa: SIM115 - the autopilot writes it until stopped
        proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
    except BaseException:
        lock.close()
        raise
    url = f"tcp:127.0.0.1:{5760 + 10 * n}" if kind == "ardupilot" else f"udpin:127.0.0.1:{14540 + n}"
    sitl = Sitl(kind, n, sysid or n + 1, url, workdir, log_path, proc, float(speed), lock, log)
    time.sleep(0.2)
    if proc.poll() is not None:
        sitl.stop()
        raise SitlError(f"{kind} SITL exited at once ({proc.returncode}): {sitl.log_tail()}")
    return sitl
