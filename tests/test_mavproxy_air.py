"""What MAVProxy costs on the swarm's radio, measured through the emulator
(tests/mavproxy_air.py: a stand-in that sends what MAVProxy sends where no autopilot
answers). Its default set-up keeps asking (parameters, home, streams) on top of its
heartbeat; the README's recommended one sends only its heartbeat. The figures in the
README come from ``python tests/mavproxy_air.py --seconds 60``; here a short run
checks what each one put on the air, counted from the emulator's capture."""

from __future__ import annotations

import pytest
from mavproxy_air import measure

# timing: frames per second on air, each frame on air within 1 s
pytestmark = [pytest.mark.processes, pytest.mark.timing]  # an emulator thread on real ptys, for 8 s


def test_recommended_mavproxy_sends_only_its_heartbeat() -> None:
    out = measure(seconds=8.0, warmup=5.0)
    default, quiet = out["default"], out["recommended"]
    for who in (default, quiet):  # what was sent went on air (the emulated air loses nothing here)
        on_air = sum(who["whole_run"]["by_message"].values())
        assert sum(who["sent"].values()) - 1 <= on_air <= sum(who["sent"].values()), who
    assert set(quiet["whole_run"]["by_message"]) == {"HEARTBEAT"}, quiet
    assert {"PARAM_REQUEST_LIST", "COMMAND_LONG", "REQUEST_DATA_STREAM", "FILE_TRANSFER_PROTOCOL"} <= set(
        default["whole_run"]["by_message"]
    ), default
    assert default["whole_run"]["frames_per_s"] > 2 * quiet["whole_run"]["frames_per_s"], out
    assert set(default["steady"]["by_message"]) >= {"HEARTBEAT", "PARAM_REQUEST_LIST"}, default
