"""The geofence's flags, shared by ``swarm agent`` and ``swarm gcs``.

Theory of operation. :func:`add_fence_arguments` declares ``--fence-floor``,
``--fence-ceiling`` and ``--fence-radius`` once (config-file keys ``fence_floor``,
``fence_ceiling``, ``fence_radius``, derived from the flags by
:mod:`swarm.cli.configfile`); :func:`fence_from` builds the
:class:`~swarm.core.flight.geofence.Geofence` they describe, or raises one UsageError naming
the flag at fault (exit 2), so that a config file's value is blamed on its key.
"""

from __future__ import annotations

import argparse

from swarm.cli.util import UsageError
from swarm.core.flight.geofence import Geofence

_DEFAULTS = Geofence()
#: flag -> (the Geofence field, what it is)
FLAGS = {
    "--fence-floor": ("floor_m", "lowest target altitude, metres above home"),
    "--fence-ceiling": ("ceiling_m", "highest target altitude, metres above home"),
    "--fence-radius": ("radius_m", "farthest target from home, metres"),
}


def add_fence_arguments(p: argparse.ArgumentParser, who: str) -> None:
    g = p.add_argument_group(f"geofence ({who} refuses a take-off or go-to outside it)")
    for flag, (key, what) in FLAGS.items():
        default = getattr(_DEFAULTS, key)
        g.add_argument(flag, type=float, default=default, metavar="M", help=f"{what} (default {default:g})")


def fence_from(a: argparse.Namespace) -> Geofence:
    """The geofence of the parsed flags.

    Raises:
        UsageError: a limit that is not a finite number, a negative floor, a ceiling not
            above the floor, a radius not positive (the flag named first).
    """
    values = {key: getattr(a, flag[2:].replace("-", "_")) for flag, (key, _) in FLAGS.items()}
    try:
        return Geofence(**values)
    except ValueError as exc:
        text = str(exc)
        flag = next(
            (f for f, (k, _) in FLAGS.items() if text.startswith(f"geofence {k[:-2]} ")), "--fence-floor"
        )
        raise UsageError(f"{flag} {values[FLAGS[flag][0]]:g}: {text}") from None


__all__ = ["FLAGS", "add_fence_arguments", "fence_from"]
