"""``swarm gcs``: the ground control station: connection protocol, web page and JSON API.

Live: ``swarm gcs --radio URL`` (a SiK radio or an emulator pty) or
``--zenoh-listen/--zenoh-connect EP...`` (Zenoh over IP). Replay:
``swarm gcs --replay CAPTURE [--speed X]`` plays a ``.tlog`` on the same page.
Several channels: ``--radio NAME=URL`` repeated (one radio per NETID); with radios,
``--zenoh-connect/--zenoh-listen`` join other stations over Zenoh (routers:
``swarm router``), their agents shown and commanded on this page too
(:class:`swarm.runtime.station.fleet.Fleet`, :mod:`swarm.runtime.station.federation`; remote
commands need the swarm key, or ``--allow-unsigned-remote``).

The page and the API answer only their own page, under this machine's names
(``--allow-host NAME`` adds one) and, beyond loopback, only with the station's token
(``--token``, ``--token-file``, or one generated and printed once in the ready
line's address ``.../?token=...``); docs/security.md.

It prints one ready line once the HTTP server listens (``--json``:
``{"event": "ready", "url", "name", "id", "link", "replay", "token", ...}``), then one line per
station event (connections, leader changes, command results; ``--json``:
``{"event": "log", "t", "kind", "text"}``). SIGINT or SIGTERM stops it (exit 130
after Ctrl-C, 0 after SIGTERM).
Bad input (a missing serial device, a port in use, a tile folder or an MBTiles
file that is not one, a damaged capture) prints one line and exits 2. A radio lost
while running (a USB radio unplugged) is waited for and reopened at the same path,
the station keeping its view of the swarm (events ``radio lost: ...`` and ``radio
back after S s``, kind ``radio``); with ``--exit-on-radio-loss`` it exits 1 instead.
With ``--key`` the station keeps its signing clock per radio, and its replay guard for
other stations' commands, in its state folder (``--state-dir``,
:mod:`swarm.cli.state_dir`): nothing recorded before a restart is taken after it.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from radios.errors import CaptureDamagedError, CaptureError
from radios.secretfile import KEY, TOKEN, secret_file_problem
from radios.smallfile import read_small_file
from swarm.cli.configfile import file_errors, read_arguments
from swarm.cli.fence_args import add_fence_arguments, fence_from
from swarm.cli.state_dir import add_state_dir_argument, node_file, open_state_dir
from swarm.cli.util import (
    StopFlag,
    UsageError,
    add_node_arguments,
    capture_damage,
    exit_when_stopped,
    guarded,
    node_options,
    parser,
    peer_watch,
    print_json,
    zenoh_security,
)
from swarm.core.wire.codes import STATION_IDS
from swarm.core.wire.message_types import NAME_RE, check_name
from swarm.errors import MessageError
from swarm.runtime.notify import Service
from swarm.runtime.station.connections import raise_file_limit
from swarm.runtime.station.security import TOKEN_RULE, check_host_name, check_token
from swarm.runtime.station.server import (
    MAX_WS_HZ,
    OSM_ATTRIBUTION,
    OSM_TILES,
    GcsServer,
    ServerConfig,
    ServerError,
)
from swarm.runtime.station.tiles import MbTilesError, open_mbtiles

PROG = "swarm gcs"


def build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "Ground control station: connects the agents that announce themselves, shows "
        "them on a map in the browser and sends them commands (JSON API at /api).",
    )
    src = add_node_arguments(
        p, title="where the swarm is: radios (and other stations), Zenoh or a capture", radios=True
    )
    src.add_argument("--replay", metavar="CAPTURE", help="play a captured flight (.tlog) instead")
    p.add_argument(
        "--http",
        default="127.0.0.1:8080",
        metavar="HOST:PORT",
        help="where the page and the API listen (default 127.0.0.1:8080; port 0: any free)",
    )
    tiles = p.add_mutually_exclusive_group()
    tiles.add_argument(
        "--tiles",
        metavar="URL_TEMPLATE",
        help=f"map tile URL with {{z}}, {{x}}, {{y}} (default {OSM_TILES}); 'none': a plain background",
    )
    tiles.add_argument("--tiles-dir", metavar="DIR", help="offline tiles DIR/{z}/{x}/{y}.png")
    tiles.add_argument(
        "--tiles-mbtiles", metavar="FILE", help="offline tiles from an MBTiles file (png, jpg or webp)"
    )
    p.add_argument(
        "--attribution", help="map attribution text (default: OpenStreetMap's; an MBTiles file's own)"
    )
    p.add_argument("--center", metavar="LAT,LON", help="initial map centre (default: the first agent)")
    p.add_argument(
        "--ws-hz",
        type=float,
        default=5.0,
        help=f"state pushes per second on the WebSocket (default 5, at most {MAX_WS_HZ:g})",
    )
    _add_security_arguments(p)
    fed = p.add_argument_group("stations joined over Zenoh (with --radio: --zenoh-connect/--zenoh-listen)")
    fed.add_argument(
        "--allow-unsigned-remote",
        action="store_true",
        help="without --key, carry out other stations' commands unsigned (anyone who reaches the "
        "Zenoh network could then command this station's agents)",
    )
    add_fence_arguments(p, "the station")
    _add_alert_arguments(p)
    add_state_dir_argument(p)
    p.add_argument("--capture", metavar="FILE", help="record the radio's traffic to a .tlog (with --radio)")
    p.add_argument("--name", default="gcs", help="station name (default gcs)")
    p.add_argument("--id", type=int, default=255, help="station system id, 251..255 (default 255)")
    p.add_argument("--speed", type=float, help="replay speed factor (default 1)")
    p.add_argument("--paused", action="store_true", help="replay: start paused")
    p.add_argument("--json", action="store_true", help="JSON lines instead of text")
    return p


# -- alerts (docs/station.md, "Alerts and link health") -----------------------------------------


def _add_alert_arguments(p: argparse.ArgumentParser) -> None:
    al = p.add_argument_group("alerts")
    al.add_argument(
        "--battery-warning", type=int, default=30, metavar="PCT", help="battery warning at or below (30 %%)"
    )
    al.add_argument(
        "--battery-critical", type=int, default=15, metavar="PCT", help="battery critical at or below (15 %%)"
    )
    al.add_argument(
        "--link-loss-alert",
        type=float,
        default=50.0,
        metavar="PCT",
        help="link alert when this share of an agent's Telemetry is lost (50 %%; cleared below 30 %%)",
    )


def _station_config(a: argparse.Namespace) -> Any:
    """The live station's settings from the alert and fence flags (UsageError for bad ones)."""
    from swarm.core.station.alerts import AlertConfig
    from swarm.core.station.model import StationConfig

    w, c, loss = a.battery_warning, a.battery_critical, a.link_loss_alert
    if not 0 <= c < w <= 100:
        raise UsageError(f"--battery-critical {c} and --battery-warning {w}: 0 <= critical < warning <= 100")
    if not (math.isfinite(loss) and 30.0 < loss <= 100.0):
        raise UsageError(f"--link-loss-alert {loss}: more than 30, at most 100 (percent)")
    alerts = AlertConfig(battery_warning=w, battery_critical=c, loss_alert=loss)
    return StationConfig(alerts=alerts, fence=a.fence)


# -- who may use the page and the API (docs/security.md) ----------------------------


def _add_security_arguments(p: argparse.ArgumentParser) -> None:
    sec = p.add_argument_group("who may use the page and the API")
    tok = sec.add_mutually_exclusive_group()
    tok.add_argument(
        "--token",
        metavar="TOKEN",
        help=f"the token the page and the API need ({TOKEN_RULE}); default: none on "
        "loopback, generated and printed once beyond it",
    )
    tok.add_argument(
        "--token-file", metavar="FILE", help="read the token from FILE (keeps it out of the process list)"
    )
    sec.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a host name the page may be opened under besides localhost and the "
        "listening address (repeatable)",
    )


def _token(a: argparse.Namespace) -> str | None:
    """The operator's token (--token, --token-file) or None. Raises UsageError."""
    if a.token_file is not None:
        try:  # a regular file of at most 4 KiB: never a FIFO or a device read for ever
            text = read_small_file(a.token_file, 4096).decode("utf-8").strip()
        except (ValueError, UnicodeDecodeError) as exc:
            why = "not UTF-8 text" if isinstance(exc, UnicodeDecodeError) else str(exc)
            raise UsageError(f"--token-file {a.token_file}: {why}") from None
        unsafe = secret_file_problem(a.token_file, TOKEN)
        if unsafe is not None:
            raise UsageError(f"--token-file {unsafe}")
        try:
            return check_token(text)
        except ValueError:
            raise UsageError(f"--token-file {a.token_file}: the token must be {TOKEN_RULE}") from None
    if a.token is not None:
        try:
            return check_token(a.token)
        except ValueError:
            raise UsageError(f"--token: {TOKEN_RULE}") from None
    return None


def _allowed_hosts(a: argparse.Namespace) -> tuple[str, ...]:
    out = []
    for name in a.allow_host:
        try:
            out.append(check_host_name(name))
        except ValueError as exc:
            raise UsageError(f"--allow-host: {exc}") from None
    return tuple(out)


def parse_http(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``[V6]:PORT`` or ``PORT``. Raises UsageError."""
    host, sep, port_s = text.rpartition(":")
    if not sep:
        host, port_s = "127.0.0.1", text
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port_s)
    except ValueError:
        raise UsageError(f"--http {text!r}: HOST:PORT (127.0.0.1:8080)") from None
    if not 0 <= port <= 65535:
        raise UsageError(f"--http {text!r}: port {port} outside 0..65535")
    return host, port


def parse_center(text: str) -> tuple[float, float]:
    try:
        lat_s, lon_s = text.split(",")
        lat, lon = float(lat_s), float(lon_s)
    except ValueError:
        raise UsageError(f"--center {text!r}: LAT,LON in degrees (47.397,8.545)") from None
    if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
        raise UsageError(f"--center {text!r}: latitude -90..90, longitude -180..180")
    return lat, lon


def _server_config(a: argparse.Namespace) -> ServerConfig:
    host, port = parse_http(a.http)
    tiles: str | None = OSM_TILES
    tiles_dir = None
    if a.tiles is not None:
        if a.tiles.lower() == "none":
            tiles = None
        elif not all(k in a.tiles for k in ("{z}", "{x}", "{y}")) or not a.tiles.startswith(
            ("http://", "https://", "/")
        ):
            raise UsageError(f"--tiles {a.tiles!r}: an http(s) URL template with {{z}}, {{x}} and {{y}}")
        else:
            tiles = a.tiles
    if a.tiles_dir is not None:
        tiles_dir = Path(a.tiles_dir)
        if not tiles_dir.is_dir():
            raise UsageError(f"--tiles-dir {a.tiles_dir}: not a directory")
        if not os.access(tiles_dir, os.R_OK | os.X_OK):
            raise UsageError(f"--tiles-dir {a.tiles_dir}: not readable")
    if not (math.isfinite(a.ws_hz) and 0 < a.ws_hz <= MAX_WS_HZ):
        raise UsageError(f"--ws-hz {a.ws_hz}: more than 0, at most {MAX_WS_HZ:g}")
    attribution = OSM_ATTRIBUTION
    mbtiles = None
    if a.tiles_mbtiles is not None:
        try:
            mbtiles = open_mbtiles(a.tiles_mbtiles)
        except MbTilesError as exc:
            raise UsageError(f"--tiles-mbtiles {exc}") from None
        attribution = mbtiles.meta.attribution
    return ServerConfig(
        host=host,
        port=port,
        tiles=tiles,
        tiles_dir=tiles_dir,
        tiles_mbtiles=mbtiles,
        attribution=a.attribution if a.attribution is not None else attribution,
        center=parse_center(a.center) if a.center else None,
        ws_hz=a.ws_hz,
        token=_token(a),
        allow_hosts=_allowed_hosts(a),
    )


def parse_radios(texts: list[str]) -> list[tuple[str, str]]:
    """``--radio [NAME=]URL`` values as (channel name, URL); unnamed ones are
    ``net<position>``. Raises UsageError (a bad or repeated name, a repeated URL)."""
    out: list[tuple[str, str]] = []
    for i, text in enumerate(texts, 1):
        name, sep, url = text.partition("=")
        if not sep or not NAME_RE.match(name) or not url:
            name, url = f"net{i}", text
        if any(n == name for n, _u in out) or any(u == url for _n, u in out):
            raise UsageError(f"--radio {text}: each channel needs its own name and radio")
        out.append((name, url))
    return out


def _check_fleet(a: argparse.Namespace) -> None:
    """Several radios, or radios and other stations over Zenoh: a.channels, no a.node."""
    a.channels, a.node = None, None
    radios = a.radio or []
    a.radio = parse_radios(radios)[0][1] if len(radios) == 1 else None
    if len(radios) > 1 or (radios and (a.zenoh_listen or a.zenoh_connect)):
        a.channels = parse_radios(radios)
        if a.capture is not None:
            raise UsageError("--capture records one radio: give one --radio (and no --zenoh-*)")
        a.radio = a.channels[0][1]
    if a.allow_unsigned_remote and a.channels is None:
        raise UsageError("--allow-unsigned-remote is for a station on radios joined over Zenoh")


def check_arguments(a: argparse.Namespace) -> None:
    ways = ", --replay CAPTURE"
    has_radio = bool(a.radio)
    _check_fleet(a)
    if a.replay is None and a.channels is None:
        a.node = node_options(a, "a station", others=ways)
    elif a.replay is None:
        a.zenoh_tls, a.zenoh_acl_file = zenoh_security(a, "station")  # the stations' own Zenoh
    elif has_radio or a.zenoh_listen or a.zenoh_connect:
        raise UsageError(f"give one of --radio URL, --zenoh-listen/--zenoh-connect EP...{ways}")
    elif a.exit_on_radio_loss:
        raise UsageError("--exit-on-radio-loss is for a station on a radio (--radio)")
    if a.replay is None and (a.speed is not None or a.paused):
        raise UsageError("--speed and --paused are for --replay")
    if a.capture is not None and a.radio is None:
        raise UsageError("--capture records a radio's traffic: it needs --radio")
    if a.replay is not None and a.key is not None:
        raise UsageError("--key is for a live station (a replay sends nothing)")
    unsafe = None if a.key is None else secret_file_problem(a.key, KEY)
    if unsafe is not None:
        raise UsageError(f"--key {unsafe}")
    try:
        check_name(a.name)
    except MessageError as exc:
        raise UsageError(f"--name: {exc}") from None
    if a.name in ("advertize", "GSAdvertize"):
        raise UsageError(f"--name {a.name!r} is a reserved key")
    if a.id not in STATION_IDS:
        raise UsageError(f"--id {a.id}: ground stations use {STATION_IDS.start}..{STATION_IDS.stop - 1}")
    if a.speed is not None and not (math.isfinite(a.speed) and 0 < a.speed <= 100):
        raise UsageError(f"--speed {a.speed}: a factor in (0, 100]")
    a.fence = fence_from(a)
    check_state_files(a)


def check_state_files(a: argparse.Namespace) -> None:
    """With --key on radios: the state folder (swarm.cli.state_dir) in ``a.state_folder``
    (None: none), and the single station's signing clock file in its node options."""
    a.state_folder = None
    if a.key is None or a.replay is not None or (a.node is not None and not a.node.on_radio):
        return
    a.state_folder = open_state_dir(a.state_dir, PROG)
    if a.state_folder is not None and a.node is not None:
        signing = node_file(a.state_folder, "gcs", a.name, a.id, "signing")
        a.node = replace(a.node, signing_state=signing)


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = read_arguments(build_parser(), argv)
    with file_errors(a):
        check_arguments(a)
        cfg = _server_config(a)
        a.station_config = _station_config(a)
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    stop = StopFlag().install()
    try:
        return _run(a, cfg, stop)
    finally:
        for sig, handler in previous.items():  # main() may run inside another program
            signal.signal(sig, handler)


def _open_station(a: argparse.Namespace) -> Any:
    if a.replay is not None:
        from swarm.runtime.station.replay import ReplayStation, load_capture

        try:
            cap = load_capture(a.replay)
        except CaptureDamagedError as exc:
            raise UsageError(capture_damage(exc)) from None
        except CaptureError as exc:
            raise UsageError(str(exc)) from None
        if cap.records == 0:
            raise UsageError(f"{a.replay}: an empty capture")
        return ReplayStation(
            cap, speed=a.speed or 1.0, name=None if a.name == "gcs" else a.name, playing=not a.paused
        ).start()
    from swarm.runtime.station.live import Station

    if a.channels is not None:
        return _open_fleet(a)
    n = a.node
    st = Station(a.name, a.id, node=n, capture=a.capture, config=a.station_config)
    try:
        return st.start()
    except CaptureError as exc:  # the capture file is the user's input too
        raise UsageError(str(exc)) from None


def _open_fleet(a: argparse.Namespace) -> Any:
    """One station per channel, merged, joined to the other stations over Zenoh."""
    from radios.signing import load_key
    from swarm.core.station.federation import fed_key
    from swarm.runtime.options import NodeOptions
    from swarm.runtime.station.federation import Federation
    from swarm.runtime.station.fleet import Fleet
    from swarm.runtime.station.live import Station

    key = fed_key(load_key(a.key)) if a.key is not None else None
    folder = a.state_folder

    def node(net: str, url: str) -> NodeOptions:
        signing = None if folder is None else node_file(folder, "gcs", a.name, a.id, "signing", net)
        return NodeOptions(radio=url, key_file=a.key, signing_state=signing)

    channels = [
        (net, Station(a.name, a.id, node=node(net, url), config=a.station_config)) for net, url in a.channels
    ]
    fleet = Fleet(a.name, a.id, channels, a.fence)
    if a.zenoh_listen or a.zenoh_connect:
        fleet.federation = Federation(
            a.name,
            connect=a.zenoh_connect,
            listen=a.zenoh_listen,
            key=key,
            tls=a.zenoh_tls,
            acl=a.zenoh_acl_file,
            accept_unsigned_commands=a.allow_unsigned_remote,
            local=fleet.local_state,
            run_local=fleet.run_local,
            on_event=fleet.note,
            state_file=None if folder is None else node_file(folder, "gcs", a.name, None, "federation"),
        )
    return fleet.start()


def _ready_line(a: argparse.Namespace, cfg: ServerConfig, station: Any, server: GcsServer) -> None:
    """The one ready line, once the server listens."""
    # the token: "none", "given" (the operator has it: not printed) or "generated"
    # (printed here, once, in the address to open)
    token = "none" if cfg.token is None else "generated" if cfg.token_generated else "given"
    ready: dict[str, Any] = {
        "event": "ready",
        "url": server.url,
        "name": station.name,
        "id": station.id,
        "link": station.describe(),
        "replay": a.replay is not None,
        "tiles": cfg.tile_template,
        "listen": f"{cfg.host}:{server.port}",
        "token": token,
    }
    if token == "generated":
        ready["open"] = server.token_url
    if a.replay is not None:
        ready["duration_s"] = round(station.capture.duration, 3)
        ready["records"] = station.capture.records
    if a.json:
        print_json(ready)
        return
    where = server.token_url if token == "generated" else server.url
    note = " (token required)" if token == "given" else ""
    if cfg.host in ("", "0.0.0.0", "::"):
        note += " (listening on every address: other machines use this one's address)"
    print(f"gcs {station.name} id={station.id} {station.describe()} {where}{note} ready", flush=True)


def _beats(station: Any, server: GcsServer) -> dict[str, tuple[float, float]]:
    """What the service watchdog watches: the station's loops (a replay has none) and the server's."""
    beats = dict(station.loop_beats()) if hasattr(station, "loop_beats") else {}
    return {**beats, **server.beats()}


def _run(a: argparse.Namespace, cfg: ServerConfig, stop: StopFlag) -> int:
    # room for the page's connections, Zenoh and the radio (the server caps its own)
    raise_file_limit()
    station = _open_station(a)
    server = None
    service: Service | None = None  # systemd's READY and WATCHDOG (docs/deployment.md, "Run as a service")
    lock = threading.Lock()

    def on_event(ev: dict[str, Any]) -> None:
        with lock:
            try:
                if a.json:
                    print_json({"event": "log", **ev})
                else:
                    print(f"[{ev['kind']}] {ev['text']}", flush=True)
            except (BrokenPipeError, ValueError):
                pass

    def on_radio(what: str, text: str) -> None:
        if what == "id_collision":  # the station's own event says it (on_event)
            return
        sep = ": " if what == "lost" else " "
        on_event({"t": round(time.time(), 3), "kind": "radio", "text": f"radio {what}{sep}{text}"})

    try:
        try:
            server = GcsServer(station, cfg).start()
        except ServerError as exc:
            raise UsageError(str(exc)) from None
        bridge = getattr(station, "bridge", None)
        for b in [st.bridge for _n, st in getattr(station, "channels", [])] or [bridge]:
            if b is not None and a.exit_on_radio_loss:
                b.cfg.reopen_radio = False  # before "ready": a radio pulled at once ends it too
        with lock:
            _ready_line(a, cfg, station, server)
        service = Service(functools.partial(_beats, station, server))
        service.ready(f"gcs {station.name} {station.describe()} {server.url} ready")
        station.add_listener(on_event)
        for b in [st.bridge for _n, st in getattr(station, "channels", [])] or [bridge]:
            if b is not None:
                b.add_listener(on_radio)
        check_peer = peer_watch(PROG, a, station)
        while not stop.wait(0.5):
            check_peer()
            if not station.running:
                return exit_when_stopped(PROG, station, "the station's thread")
    finally:
        if service is not None:
            service.stopping()
        if server is not None:
            server.stop()
        station.stop()
    return stop.exit_code()
