"""Replays across restarts, on the real radio emulator (issue 27): a signed leader and
member, the leader's frames recorded from the air, the leader killed, the member
restarted, then the recording (frames less than a minute old) replayed through a rogue
radio. Before the fix the restarted member's verifier had never heard the dead
leader's stream and took the recording for a live one: the member followed the dead
leader. Then the other half: the dead leader comes back (a live new stream: heard at
once), and both agents restarted together do not lock each other out.

The agents keep their state where the service unit puts it (``$STATE_DIRECTORY``),
here a folder of the test's own.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from net_helpers import wait_until

from radios.link import open_link
from radios.mavlink import IFLAG_SIGNED, STX_V2
from radios.signing import EPOCH_2015
from radios.tlog import read_tlog
from swarm.cli.procs import Child, json_events, start_emulator

pytestmark = pytest.mark.processes  # agent processes on the emulated radios

ELECT_DEADLINE = 90.0  # the radios' hop lock and the paper's windows: about 10 s seen
RECORD_S = 30.0  # the recording replayed: the dead leader's last 30 s on the air
SETTLED = ("LEADER", "MEMBER")


def states(child: Child) -> list[dict[str, Any]]:
    return json_events(child.lines, "state")


def pair_leader(a: Child, b: Child) -> int | None:
    """The leader both agents name, one LEADER and one MEMBER; else None."""
    last = [states(c)[-1] if states(c) else None for c in (a, b)]
    if any(s is None or s["phase"] not in SETTLED for s in last):
        return None
    leaders = {s["leader"] for s in last if s is not None}
    phases = sorted(s["phase"] for s in last if s is not None)
    return leaders.pop() if len(leaders) == 1 and phases == ["LEADER", "MEMBER"] else None


def signed_frames_of(tlog: Path, sysid: int, since: float, until: float) -> list[tuple[float, bytes]]:
    out = []
    for rec in read_tlog(tlog):
        raw = bytes(rec.raw)
        if since <= rec.t <= until and raw[0] == STX_V2 and raw[2] & IFLAG_SIGNED and raw[5] == sysid:
            out.append((rec.t, raw))
    return out


def signing_age_s(raw: bytes) -> float:
    """How old a signed frame's timestamp is by this machine's clock."""
    ts = int.from_bytes(raw[-12:-6], "little")
    return time.time() - (EPOCH_2015 + ts / 100_000)


@pytest.mark.timeout(300)
def test_a_dead_leaders_recording_is_not_followed_by_a_member_restarted_after_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    state = tmp_path / "state"
    state.mkdir(mode=0o700)
    monkeypatch.setenv("STATE_DIRECTORY", str(state))  # what systemd gives the units
    key = tmp_path / "swarm.key"
    key.write_text("replay across restarts\n")
    key.chmod(0o600)
    tlog = tmp_path / "air.tlog"
    (tmp_path / "radios").mkdir()
    emu, radios = start_emulator(3, tmp_path / "radios", "--capture", str(tlog), "--seed", "16")
    children: dict[int, Child] = {}

    def agent(k: int) -> Child:
        argv = ["agent", "--name", f"agent{k}", "--id", str(k), "--radio", radios[k - 1]]
        c = children[k] = Child([*argv, "--key", str(key), "--json"], name=f"agent{k}")
        assert json.loads(c.wait_lines(1, 60)[0])["event"] == "ready"
        return c

    def kill(k: int) -> None:
        os.killpg(children[k].proc.pid, signal.SIGKILL)
        children[k].proc.wait(10)
        children[k].stop()

    try:
        agent(1), agent(2)
        lead = wait_until(
            lambda: pair_leader(children[1], children[2]),
            "the signed pair to elect a leader",
            ELECT_DEADLINE,
            children=list(children.values()),
        )
        member = 3 - lead
        time.sleep(2.0)  # a few more of the leader's heartbeats on the air
        killed_at = time.time()
        kill(lead)  # the leader dies for good ...
        kill(member)  # ... and the member restarts after it (kill -9: nothing saved at a stop)
        restarted = agent(member)
        recording = signed_frames_of(tlog, lead, killed_at - RECORD_S, killed_at)
        frames = [raw for _t, raw in recording]
        assert len(frames) >= 10, len(frames)  # its heartbeats to the member, at 1 Hz at least

        # the recording, through a rogue radio, while it is less than a minute old
        rogue = open_link(radios[2])
        replay_start = time.time()
        try:
            for raw in frames:
                rogue.send(raw)
                time.sleep(len(raw) / 3000.0)
        finally:
            rogue.close()
        # every replayed frame went out on the air (the emulator records what it sends) ...
        wait_until(
            lambda: len(signed_frames_of(tlog, lead, replay_start, time.time())) >= len(frames),
            "the replayed frames on the air",
            30.0,
            0.5,
        )
        # ... inside the minute: the MAVLink rule alone does not refuse them
        assert max(signing_age_s(raw) for raw in frames) < 60.0
        time.sleep(5.0)  # longer than a heartbeat period: room for the replay to take effect
        followed = [s for s in states(restarted) if s["leader"] == lead]
        assert not followed, f"the restarted member followed the dead leader: {followed[:2]}"

        # the dead leader comes back (a live stream): heard at once, one swarm again
        rejoin_from = time.monotonic()
        agent(lead)
        wait_until(
            lambda: pair_leader(children[1], children[2]),
            "the leader back and the member in one swarm",
            ELECT_DEADLINE,
            children=list(children.values()),
        )
        print(f"\nleader restarted: one swarm again after {time.monotonic() - rejoin_from:.1f} s")

        # both restarted at once: neither locks the other out
        kill(1), kill(2)
        together_from = time.monotonic()
        agent(1), agent(2)
        wait_until(
            lambda: pair_leader(children[1], children[2]),
            "both agents, restarted together, to elect a leader",
            ELECT_DEADLINE,
            children=list(children.values()),
        )
        print(f"both restarted: one swarm again after {time.monotonic() - together_from:.1f} s")
    finally:
        for c in children.values():
            c.stop()
        emu.stop()
    for c in children.values():
        assert not [e for e in c.errors if "Traceback" in e], (c.name, c.errors[-5:])
