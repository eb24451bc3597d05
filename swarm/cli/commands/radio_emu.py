"""``swarm radio-emu``: a network of emulated SiK radios on pseudo terminals."""

from __future__ import annotations

import argparse
import sys

from radios.emulator import Emulator
from radios.emulator_config import EmulatorConfig, check_capture_path, parse_param
from radios.errors import CaptureError, ConfigError
from swarm.cli.configfile import read_arguments
from swarm.cli.util import StopFlag, UsageError, guarded, parser

PROG = "swarm radio-emu"


def build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "Emulate N SiK radios: DIR/radio0..N-1 are serial ports of radios "
        "sharing one emulated air. Runs until SIGINT/SIGTERM. Unplug a radio's "
        "cable and plug it back at run time by writing lines to the FIFO "
        "DIR/control: 'unplug I [FOR_S]', 'replug I' (the radio stays powered "
        "and keeps its place on the air; one line on stdout for each), and "
        "change the loss with 'loss P'.",
    )
    p.add_argument("--nodes", type=int, required=True, help="number of radios")
    p.add_argument("--dir", required=True, help="existing directory for the radio<i> links")
    p.add_argument(
        "--air-speed",
        type=int,
        default=64,
        metavar="KBPS",
        help="AIR_SPEED in kbit/s, rounded up as the firmware does (default 64)",
    )
    p.add_argument(
        "--serial-speed",
        type=int,
        default=57600,
        metavar="BAUD",
        help="serial rate of every radio (default 57600)",
    )
    p.add_argument(
        "--netid",
        type=int,
        nargs="+",
        default=[25],
        metavar="ID",
        help="NETID for all radios, or one per radio (default 25)",
    )
    p.add_argument(
        "--firmware",
        choices=("standard", "multipoint"),
        help="medium access: standard TDM pair, or multipoint slots "
        "(default: standard for 2 radios, multipoint for more)",
    )
    _add_channel_arguments(p)
    p.add_argument("--capture", metavar="FILE", help="write every frame put on air to a .tlog")
    p.add_argument(
        "--capture-status",
        type=int,
        metavar="I",
        help="with --capture: also record radioI's RADIO_STATUS reports (a ground station's radio)",
    )
    p.add_argument(
        "--stats-json", metavar="FILE", help="write counters and channel utilisation (every 2 s and at exit)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed for loss and timing")
    return p


def _add_channel_arguments(p: argparse.ArgumentParser) -> None:
    """The air between the radios, and what the radios do with it."""
    p.add_argument(
        "--loss", type=float, default=0.0, metavar="P", help="uniform packet loss probability per receiver"
    )
    p.add_argument("--burst-loss", metavar="P_GB,P_BG[,LG,LB]", help="Gilbert-Elliott bursty loss per link")
    p.add_argument(
        "--positions",
        metavar="FILE",
        help='JSON {"0": [x, y, z], ...} in metres, re-read when it changes: '
        "range loss and RSSI from distance",
    )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="any SiK parameter for every radio, e.g. ECC=1, MAX_WINDOW=33, MAVLINK=0",
    )
    p.add_argument(
        "--flow-control",
        action="store_true",
        help="model the CTS line: a host writing too fast is held back "
        "instead of losing bytes in the radio's full buffer",
    )


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    args = read_arguments(build_parser(), argv, config=False)
    try:
        params = dict(parse_param(x) for x in args.param)
        cfg = EmulatorConfig(
            nodes=args.nodes,
            directory=args.dir,
            air_speed=args.air_speed,
            serial_speed=args.serial_speed,
            netids=args.netid,
            firmware=args.firmware,
            loss=args.loss,
            burst_loss=args.burst_loss,
            positions=args.positions,
            params=params,
            flow_control=args.flow_control,
            capture=args.capture,
            capture_status=args.capture_status,
            stats_json=args.stats_json,
            seed=args.seed,
        )
        if args.capture:
            check_capture_path(args.capture)
        if args.stats_json:
            check_capture_path(args.stats_json)
        emu = Emulator(cfg)
        stop = StopFlag().install()
        ports = emu.open()
    except CaptureError as exc:
        raise UsageError(str(exc)) from None
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    try:
        model = emu.model
        assert model is not None
        for i, (link, pty) in enumerate(ports):
            c = model.radios[i].cfg
            print(
                f"radio{i} {link} -> {pty} netid={c.netid} air={c.air_kbps}kbps "
                f"serial={c.serial_baud} firmware={c.firmware}",
                flush=True,
            )
        emu.on_event = lambda text: print(text, flush=True)
        emu.run(stop.event)
        st = emu.stats()
        print(
            f"stopped after {st['elapsed_s']:.1f} s: channel utilisation "
            f"{100 * st['utilisation']:.1f}%, round {1000 * st['round_s']:.0f} ms, "
            f"{st['frames_captured']} frames captured",
            file=sys.stderr,
            flush=True,
        )
    finally:
        emu.close()
    return stop.exit_code()
