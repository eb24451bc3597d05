"""The air: a network of SiK radios as a pure discrete-event model.

Theory of operation
-------------------
This package owns everything between the serial pins of N radios: serial pacing,
the radios' buffers, the MAVLink-aware packetiser, the TDM medium access, the
channel (one transmission at a time, collisions, half duplex, NETID, loss) and
RADIO_STATUS injection. It does no I/O and reads no clock: the caller feeds bytes
with :meth:`AirModel.host_write` at a time ``now``, moves time forward with
:meth:`AirModel.advance`, collects each radio's serial output with
:meth:`AirModel.take_output`, and sleeps until :meth:`AirModel.next_deadline`.
The pty emulator (:mod:`radios.emulator`) drives it in real time; the swarm's
deterministic simulator drives the very same model in virtual time.

Each radio runs the firmware's loop, reduced to the moments where it can act:

* TDM (tdm.c): TRANSMIT(W) -> SILENCE(S) -> RECEIVE(W) -> SILENCE(S). Whenever a
  radio may transmit (its own window, or the peer's window when the peer yielded
  it "bonus" ticks) it sends one packet at once: user data, a statistics packet
  twice a second, or a zero-length packet that yields the rest of the window.
  Every packet's 2-byte trailer says how many ticks its sender has left, and the
  receiver re-synchronises its own state to it (``sync_tx_windows``). Two radios
  thus form the standard pair; three or more standard radios on one NETID each
  sync to whatever they heard last and collide, as the real firmware does.
* Multipoint firmware: node ids own windows in turn (NODECOUNT slots of W+S),
  packets carry a destination (0xFFFF broadcast); idle nodes stay silent except
  the base (node 0) whose packet keeps the network in sync. No bonus ticks.
* Packetiser (packet.c): with MAVLINK framing it waits for a whole frame (but no
  longer than the frame's serial time), packs as many whole frames as fit, sends
  non-MAVLink bytes as they come, and splits frames too large for one packet.
* Channel: a packet occupies the air for flight(n) = L + n·tpb ticks; a receiver
  hears it only if it has the same NETID and air settings, is not transmitting
  itself meanwhile, no other audible packet overlaps it (collision), it is locked
  to the hopping sequence (an unlocked radio is on the right channel with
  probability 1/NUM_CHANNELS per packet) and no loss model drops it.
* Serial side: bytes from the host reach the radio at the serial rate and are
  dropped when the 1850-byte input buffer is full (``srx``); received data leaves
  at the serial rate through a 645-byte output buffer, truncated when full
  (``stx``). A HEARTBEAT sent from the host makes the radio inject RADIO_STATUS
  (rssi, remrssi, txbuf % free, noise, remnoise, rxerrors) into its serial output.

AES builds (``RadioConfig.key`` not empty; tdm.c, packet.c, freq_hopping.c): the
hopping sequence is seeded by a CRC-16 of the key instead of the NETID, so a radio
with another key (or none) shares a channel with this one only by chance: it hears
a packet with probability 1/NUM_CHANNELS and never locks. Data and injected replies
are encrypted: a receiver with another key writes garbage of the same length to its
host. ``RT`` commands travel in clear and any radio that hears one runs it, key or
no key. Packets carry at most 31 bytes of data (packet_get_next) and need 16 more
bytes of window.

Not modelled (documented simplifications): duty cycle and LBT, temperature, the
per-channel frequency plan (NETIDs never interfere), opportunistic resend (off
since 2.0), CTS unless ``flow_control`` is set by the caller.

The package splits by responsibility: :mod:`radios.air.radio` (configuration and
per-radio state), :mod:`radios.air.serial` (serial pacing and buffers),
:mod:`radios.air.packetiser` (what a packet carries) and :mod:`radios.air.model`
(the event queue, TDM medium access and the channel). The names other code uses
are importable from ``radios.air``.
"""

from __future__ import annotations

from radios.air.model import AirModel
from radios.air.radio import (
    BROADCAST,
    INJECT_MAX,
    PREAMBLE_BYTES,
    RADIO_STATUS_COMPID,
    RADIO_STATUS_SYSID,
    ATHandler,
    LossModel,
    Packet,
    RadioConfig,
    RadioState,
    RadioStats,
)

__all__ = [
    "BROADCAST",
    "INJECT_MAX",
    "PREAMBLE_BYTES",
    "RADIO_STATUS_COMPID",
    "RADIO_STATUS_SYSID",
    "ATHandler",
    "AirModel",
    "LossModel",
    "Packet",
    "RadioConfig",
    "RadioState",
    "RadioStats",
]
