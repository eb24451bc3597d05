"""TDM rules of one radio (SiK tdm.c): its states, its slot, and following a peer.

Theory of operation
-------------------
A standard radio cycles TRANSMIT(W) -> SILENCE(S) -> RECEIVE(W) -> SILENCE(S)
(:func:`next_state`). Every packet's trailer says how many ticks its sender has left
in its state, and a receiver re-synchronises to it (:func:`sync_tx_windows`): it
enters RECEIVE for that long, or, if the sender gave its window away (a bonus
packet), takes the turn to send. A multipoint radio owns one window in a round of
NODECOUNT slots counted from the start of the model (:func:`multipoint_slot`).
Before sending, a radio listens: a preamble it has detected on the air
(:func:`audible_busy_until`) makes it hold off. Pure functions of one
:class:`~radios.air.radio.RadioState` and the packets on the air; the model
schedules the events they imply.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from radios.air.radio import PREAMBLE_BYTES, RX, SILENCE1, SILENCE2, TX, Packet, RadioState
from radios.sik.timing import TICK_S


def next_state(r: RadioState, t: float) -> None:
    """A standard radio's state ended at ``t``: enter the next one."""
    r.state = (r.state + 1) % 4
    dur = r.t.window_s if r.state in (TX, RX) else r.t.silence_s
    r.state_end = t + dur
    r.bonus = False
    r.yielded = False
    r.wait_until = t


def sync_tx_windows(r: RadioState, pkt: Packet, t: float) -> None:
    """sync_tx_windows() of tdm.c: follow the state ``pkt``'s trailer announces (the
    caller schedules the new ``state_end``)."""
    window_s = pkt.window * TICK_S
    if pkt.bonus:
        if r.state == SILENCE1:
            r.state_end = t + r.t.silence_s
        elif r.state in (RX, SILENCE2):
            r.state = SILENCE2
            r.state_end = t + TICK_S
        else:
            r.state = TX
            r.state_end = t + window_s
    else:
        r.state = RX
        r.state_end = t + window_s
    r.bonus = r.state == RX and len(pkt.payload) == 0
    if r.state != TX:
        r.yielded = False


def audible_busy_until(
    r: RadioState, t: float, airing: Sequence[Packet], radios: Sequence[RadioState]
) -> float | None:
    """End of a packet whose preamble ``r`` has detected by ``t``. Detecting a
    preamble takes PREAMBLE_BYTES byte times, so radios that start within that
    time of each other do not see each other and collide."""
    end = None
    detect = PREAMBLE_BYTES * r.t.ticks_per_byte * TICK_S
    for p in airing:
        if (
            p.sender != r.index
            and p.t_start + detect <= t < p.t_end
            and radios[p.sender].cfg.compatible(r.cfg)
        ):
            end = p.t_end if end is None else max(end, p.t_end)
    return end


def multipoint_slot(r: RadioState, t: float, start: float) -> tuple[bool, float, float]:
    """Multipoint: (inside own transmit window, end of that window, start of the
    next own window), with rounds counted from ``start``. Computed on whole ticks so
    that waking at an edge always lands inside the window."""
    w = r.t.tx_window_width
    slot = w + r.t.silence_period
    count = max(r.cfg.node_count, 1)
    rnd = slot * count
    now_tick = math.floor((t - start) / TICK_S + 1e-6)
    mine = now_tick - now_tick % rnd + (r.cfg.node_id % count) * slot
    if mine <= now_tick < mine + w:
        return True, start + (mine + w) * TICK_S, start + (mine + rnd) * TICK_S
    nxt = mine if now_tick < mine else mine + rnd
    return False, start + nxt * TICK_S, start + nxt * TICK_S


__all__ = ["audible_busy_until", "multipoint_slot", "next_state", "sync_tx_windows"]
