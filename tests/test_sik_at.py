"""The radio-side AT interpreter, driven with explicit times (no real clock, no sleeps)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from radios.errors import ConfigError
from radios.sik.at import (
    REMOTE_REPLY_MAX,
    ATEngine,
    ATOutput,
    split_remote_target,
)
from radios.sik.param_table import BROADCAST
from radios.sik.params import SikParams

ATI6 = "silence_period: 260\ntx_window_width: 7140\nmax_data_packet_length: 252"
ATI7 = "L/R RSSI: 180/175  L/R noise: 40/42 pkts: 10  txe=0 rxe=0 stx=0 srx=0 ecc=0/0"


def engine(
    flavour: str = "standard",
    *,
    boot_time: float | None = 0.0,
    board: str = "HM-TRP",
    node_id: int | None = None,
    band: int = 915,
) -> ATEngine:
    return ATEngine(
        SikParams(flavour, band=band),
        flavour=flavour,
        board=board,
        ati6=lambda: ATI6,
        ati7=lambda: ATI7,
        node_id=node_id,
        boot_time=boot_time,
    )


def enter(e: ATEngine, t: float = 10.0) -> float:
    """Put ``e`` into command mode with a correct +++ at ``t``; return the time after."""
    assert e.feed(b"+++", t).to_host == b""
    out = e.poll(t + 1.0)
    assert out.to_host.endswith(b"OK\r\n")
    assert e.in_command_mode
    return t + 1.0


def cmd(e: ATEngine, line: bytes, t: float = 20.0) -> bytes:
    """Run one command line; return what the radio printed after the echo."""
    out = e.feed(line + b"\r", t)
    echo = line.upper() + b"\r\n"
    assert out.to_host.startswith(echo), out.to_host
    return out.to_host[len(echo) :]


@pytest.fixture
def at() -> ATEngine:
    e = engine()
    enter(e)
    return e


# -- entering command mode ----------------------------------------------------------------


def test_plus_plus_plus_with_guard_times() -> None:
    e = engine()
    out = e.feed(b"+++", 1.0)  # 1 s after boot: the guard before is met
    assert out == ATOutput(to_air=b"+++")  # the pluses are not swallowed
    assert e.next_deadline() == 2.0
    assert e.poll(1.999).to_host == b""
    assert not e.in_command_mode
    assert e.poll(2.0).to_host == b"OK\r\n"
    assert e.in_command_mode
    assert e.next_deadline() is None


def test_guard_after_boot_violated() -> None:
    e = engine()
    e.feed(b"+++", 0.5)
    assert e.poll(5.0).to_host == b""
    assert not e.in_command_mode


def test_guard_before_violated_by_data() -> None:
    e = engine()
    e.feed(b"hello", 3.0)
    e.feed(b"+++", 3.9)
    assert e.next_deadline() is None
    assert e.poll(10.0).to_host == b""
    assert not e.in_command_mode
    # after a real second of silence it works
    e.feed(b"+++", 11.0)
    assert e.poll(12.0).to_host == b"OK\r\n"


def test_guard_after_violated_by_data() -> None:
    e = engine()
    e.feed(b"+++", 2.0)
    out = e.feed(b"x", 2.5)
    assert out.to_air == b"x"
    assert e.poll(10.0).to_host == b""
    assert not e.in_command_mode


def test_extra_plus_restarts_the_guard() -> None:
    e = engine()
    e.feed(b"+++", 2.0)
    e.feed(b"+", 2.5)
    assert e.poll(3.4).to_host == b""
    assert e.poll(3.5).to_host == b"OK\r\n"


def test_four_pluses_at_once() -> None:
    e = engine()
    e.feed(b"++++", 2.0)
    assert e.poll(3.0).to_host == b"OK\r\n"


def test_any_gap_between_pluses() -> None:
    e = engine()
    e.feed(b"+", 2.0)
    e.feed(b"+", 5.0)
    e.feed(b"+", 9.0)
    assert e.poll(10.0).to_host == b"OK\r\n"


def test_other_byte_between_pluses_resets() -> None:
    e = engine()
    assert e.feed(b"++x+", 2.0).to_air == b"++x+"
    assert e.poll(10.0).to_host == b""
    e.feed(b"+", 10.5)  # the idle second has passed since the last byte
    e.feed(b"++", 10.6)
    assert e.poll(11.6).to_host == b"OK\r\n"


def test_no_boot_time_means_idle_since_long_ago() -> None:
    e = engine(boot_time=None)
    e.feed(b"+++", 0.0)
    assert e.poll(1.0).to_host == b"OK\r\n"


def test_byte_at_a_time_equals_whole_chunk() -> None:
    whole, split = engine(), engine()
    data = b"abc+++"
    whole_out = whole.feed(data, 5.0)
    split_air = b"".join(split.feed(bytes([c]), 5.0).to_air for c in data)
    assert whole_out.to_air == split_air == data
    assert whole.poll(6.0).to_host == split.poll(6.0).to_host == b""  # abc too close


def test_time_going_backwards_is_clamped() -> None:
    e = engine()
    e.feed(b"+++", 5.0)
    assert e.poll(4.0).to_host == b""
    assert e.poll(6.0).to_host == b"OK\r\n"


# -- line discipline ----------------------------------------------------------------------


def test_echo_is_upper_case(at: ATEngine) -> None:
    out = at.feed(b"ati1\r", 20.0)
    assert out.to_host == b"ATI1\r\n2.2\r\n"
    assert out.to_air == b""  # command mode: nothing forwarded


def test_backspace_and_delete_erase(at: ATEngine) -> None:
    out = at.feed(b"ATX\x08I1\r", 20.0)
    assert out.to_host == b"ATX\b \bI1\r\n2.2\r\n"
    out = at.feed(b"ATX\x7fI1\r", 21.0)
    assert out.to_host == b"ATX\b \bI1\r\n2.2\r\n"
    assert at.feed(b"\x08\x7f", 22.0).to_host == b""  # nothing to erase: no echo


def test_lf_and_control_bytes_ignored(at: ATEngine) -> None:
    assert at.feed(b"A\x01T\r\n", 20.0).to_host == b"AT\r\nOK\r\n"


def test_empty_and_foreign_lines_get_no_reply(at: ATEngine) -> None:
    assert at.feed(b"\r", 20.0).to_host == b"\r\n"
    assert at.feed(b"hello\r", 20.0).to_host == b"HELLO\r\n"
    assert at.feed(b"A\r", 20.0).to_host == b"A\r\n"
    assert at.in_command_mode


def test_sixteen_chars_fit(at: ATEngine) -> None:
    line = b"ATI5XXXXXXXXXXXX"  # 16 chars; only the character after ATI counts
    assert len(line) == 16
    reply = cmd(at, line)
    assert reply.startswith(b"S0:FORMAT=26\r\n")


def test_seventeenth_char_returns_to_data_mode(at: ATEngine) -> None:
    out = at.feed(b"A" * 16 + b"B" + b"xyz", 20.0)
    assert out.to_host == b"A" * 16  # echo only, no reply
    assert out.to_air == b"xyz"  # data mode again
    assert not at.in_command_mode


def test_overflow_quirk_needs_a_fresh_idle_second(at: ATEngine) -> None:
    at.feed(b"A" * 17, 20.0)
    # The guard timer is not running after an overflow: the first '+' only starts it.
    at.feed(b"+++", 30.0)
    assert at.poll(40.0).to_host == b""
    at.feed(b"+++", 41.0)
    assert at.poll(42.0).to_host == b"OK\r\n"


# -- commands -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"AT", b"OK\r\n"),
        (b"ATI", b"SiK 2.2 on HM-TRP\r\n"),
        (b"ATI0", b"SiK 2.2 on HM-TRP\r\n"),
        (b"ATI1", b"2.2\r\n"),
        (b"ATI2", b"78\r\n"),
        (b"ATI3", b"145\r\n"),
        (b"ATI4", b"2\r\n"),
        (b"ATI6", ATI6.replace("\n", "\r\n").encode() + b"\r\n"),
        (b"ATI7", ATI7.encode() + b"\r\n"),
        (b"ATI8", b"ERROR\r\n"),
        (b"ATI9", b"ERROR\r\n"),
        (b"ATS2?", b"64\r\n"),
        (b"ATS?", b"26\r\n"),  # no number is S0
        (b"ATS258?", b"64\r\n"),  # the register number is a uint8_t: 258 is S2
        (b"ATS15?", b"131\r\n"),
        (b"ATS16?", b"ERROR\r\n"),
        (b"ATS16=1", b"ERROR\r\n"),
        (b"ATS0=26", b"ERROR\r\n"),
        (b"ATS1=56", b"ERROR\r\n"),
        (b"ATS2=257", b"ERROR\r\n"),
        (b"ATS2", b"ERROR\r\n"),
        (b"ATS2!", b"ERROR\r\n"),
        (b"ATS1=115", b"OK\r\n"),
        (b"AT&W", b"OK\r\n"),
        (b"AT&F", b"OK\r\n"),
        (b"AT&T", b""),
        (b"AT&T=RSSI", b""),
        (b"AT&T=TDM", b""),
        (b"AT&T=FOO", b"ERROR\r\n"),
        (b"AT&X", b"ERROR\r\n"),
        (b"AT&UPDATE", b"ERROR\r\n"),
        (b"AT+P=1", b"ERROR\r\n"),
        (b"ATQ", b"ERROR\r\n"),
    ],
)
def test_command_replies(at: ATEngine, line: bytes, reply: bytes) -> None:
    assert cmd(at, line) == reply
    assert at.in_command_mode


def test_ati5_lists_ram_values(at: ATEngine) -> None:
    cmd(at, b"ATS3=77")
    lines = cmd(at, b"ATI5").decode().split("\r\n")
    assert lines[-1] == ""
    assert len(lines[:-1]) == 16
    assert lines[0] == "S0:FORMAT=26"
    assert lines[3] == "S3:NETID=77"
    assert lines[15] == "S15:MAX_WINDOW=131"


@pytest.mark.parametrize(
    ("board", "band", "ati2", "ati3"),
    [
        ("RFD900A", 915, b"67", b"145"),
        ("3DR1060", 433, b"81", b"67"),
        ("RFD900P", 868, b"130", b"134"),
        ("HB1060", 470, b"80", b"71"),
    ],
)
def test_board_and_band(board: str, band: int, ati2: bytes, ati3: bytes) -> None:
    e = engine(board=board, band=band)
    enter(e)
    assert cmd(e, b"ATI2") == ati2 + b"\r\n"
    assert cmd(e, b"ATI3") == ati3 + b"\r\n"
    assert cmd(e, b"ATI") == f"SiK 2.2 on {board}\r\n".encode()


def test_value_parsing_stops_at_non_digit(at: ATEngine) -> None:
    assert cmd(at, b"ATS3=x") == b"OK\r\n"
    assert at.params.ram[3] == 0
    assert cmd(at, b"ATS3=12ab") == b"OK\r\n"
    assert at.params.ram[3] == 12


def test_set_boot_param_vs_now_param(at: ATEngine) -> None:
    assert cmd(at, b"ATS2=128") == b"OK\r\n"
    assert at.params.ram[2] == 128
    assert at.params.active[2] == 64  # AIR_SPEED waits for a reboot
    assert cmd(at, b"ATS4=10") == b"OK\r\n"
    assert at.params.ram[4] == 11
    assert at.params.active[4] == 11  # TXPOWER applies immediately
    assert cmd(at, b"ATS4?") == b"11\r\n"


def test_save_and_reboot_apply_air_speed_rounding(at: ATEngine) -> None:
    assert cmd(at, b"ATS2=100") == b"OK\r\n"
    assert cmd(at, b"AT&W") == b"OK\r\n"
    out = at.feed(b"ATZ\rATI\r", 30.0)
    assert out.to_host == b"ATZ\r\n"  # no reply; the bytes after ATZ are lost in the reboot
    assert out.reboot
    assert not at.in_command_mode
    assert at.params.active[2] == 128
    # the guard restarts at boot: +++ right away does nothing
    at.feed(b"+++", 30.5)
    assert at.poll(35.0).to_host == b""
    enter(at, 40.0)
    assert cmd(at, b"ATS2?", 42.0) == b"128\r\n"


def test_reboot_without_save_discards(at: ATEngine) -> None:
    cmd(at, b"ATS3=99")
    at.feed(b"ATZ\r", 30.0)
    assert at.params.ram[3] == 25


def test_factory_defaults_into_ram_only(at: ATEngine) -> None:
    cmd(at, b"ATS2=128")
    cmd(at, b"AT&W")
    at.feed(b"ATZ\r", 30.0)
    enter(at, 40.0)
    assert cmd(at, b"AT&F", 42.0) == b"OK\r\n"
    assert cmd(at, b"ATS2?", 42.0) == b"64\r\n"
    assert cmd(at, b"ATS8?", 42.0) == b"0\r\n"  # the raw default, before the boot rewrite
    assert at.params.active[2] == 128
    assert at.params.eeprom[2] == 128


def test_ato_returns_to_data_mode(at: ATEngine) -> None:
    out = at.feed(b"ATO\rdata", 20.0)
    assert out.to_host == b"ATO\r\n"
    assert out.to_air == b"data"
    assert not at.in_command_mode
    at.feed(b"+++", 22.0)
    assert at.poll(23.0).to_host == b"OK\r\n"


def test_rssi_debug_prints_every_half_second(at: ATEngine) -> None:
    cmd(at, b"AT&T=RSSI", 20.0)
    assert at.debug_rssi
    assert at.next_deadline() == 20.5
    assert at.poll(20.5).to_host == ATI7.encode() + b"\r\n"
    at.feed(b"ATO\r", 20.6)  # it keeps printing in data mode
    assert at.poll(21.0).to_host == ATI7.encode() + b"\r\n"
    at.feed(b"+++", 25.0)
    assert at.poll(26.0).to_host.startswith(b"OK\r\n")  # then a (single) late RSSI line
    assert at.in_command_mode
    cmd(at, b"AT&T", 26.0)
    assert not at.debug_rssi
    assert at.next_deadline() is None
    assert at.poll(30.0).to_host == b""


def test_tdm_debug_flag(at: ATEngine) -> None:
    cmd(at, b"AT&T=TDM")
    assert at.debug_tdm
    cmd(at, b"AT&T=TDM")
    assert not at.debug_tdm


# -- remote commands ----------------------------------------------------------------------


def test_rt_command_is_handed_out_once(at: ATEngine) -> None:
    out = at.feed(b"rti5\rATI1\r", 20.0)
    assert out.to_host == b"RTI5\r\n"  # the local radio prints nothing more
    assert out.remote_command == "RTI5"
    assert at.in_command_mode
    # the rest of the chunk arrived while the command was pending: dropped
    assert at.feed(b"ATI1\r", 21.0).remote_command is None


def test_multipoint_rt_keeps_target(at: ATEngine) -> None:
    e = engine("multipoint")
    enter(e)
    assert e.feed(b"RTI5,2\r", 20.0).remote_command == "RTI5,2"


def test_split_remote_target() -> None:
    assert split_remote_target("RTI5,2") == ("RTI5", 2)
    assert split_remote_target("RTS3=5,12") == ("RTS3=5", 12)
    assert split_remote_target("RTI5") == ("RTI5", BROADCAST)
    assert split_remote_target("RTI5,") == ("RTI5", 0)
    assert split_remote_target("RTI,70000") == ("RTI", 70000 & 0xFFFF)


def test_run_remote_output_format() -> None:
    remote = engine()
    result = remote.run_remote("RTI5")
    assert not result.reboot
    text = result.output.decode()
    assert b"\r" not in result.output  # bare \n, no echo
    assert text.startswith("S0:FORMAT=26\nS1:SERIAL_SPEED=57\n")
    assert len(result.output) == REMOTE_REPLY_MAX  # ATI5 at 915 defaults is exactly 252 B
    assert text.endswith("S15:MAX_WINDOW=131\n")
    assert remote.run_remote("RTI").output == b"SiK 2.2 on HM-TRP\n"
    assert remote.run_remote("RT").output == b"OK\n"
    assert remote.run_remote("RTI6").output == ATI6.encode() + b"\n"
    assert remote.run_remote("RTQ").output == b"ERROR\n"
    assert remote.run_remote("XYZ").output == b""


def test_run_remote_caps_at_252_bytes() -> None:
    remote = engine()
    remote.params.set(8, 1_000_000)  # longer values: ATI5 no longer fits
    result = remote.run_remote("RTI5")
    assert len(result.output) == REMOTE_REPLY_MAX
    assert not result.output.endswith(b"\n")  # cut mid-line, like the firmware


def test_run_remote_sets_saves_and_reboots() -> None:
    remote = engine()
    assert remote.run_remote("RTS2=100").output == b"OK\n"
    assert remote.run_remote("RT&W").output == b"OK\n"
    result = remote.run_remote("RTZ", 50.0)
    assert result.reboot and result.output == b""
    assert remote.params.active[2] == 128
    assert not remote.in_command_mode


def test_run_remote_in_command_mode_radio() -> None:
    remote = engine()
    enter(remote)
    assert remote.run_remote("RTS3=5").output == b"OK\n"
    assert remote.in_command_mode
    assert remote.params.ram[3] == 5


def test_multipoint_prefixes_every_line() -> None:
    e = engine("multipoint")
    e.feed(b"+++", 5.0)
    assert e.poll(6.0).to_host == b"[1] OK\r\n"
    assert cmd(e, b"ATI") == b"[1] MP SiK 2.2 on HM-TRP\r\n"
    assert cmd(e, b"ATS18=4") == b"[1] OK\r\n"
    assert cmd(e, b"ATS15=3") == b"[3] OK\r\n"  # NODEID applies now, even to this reply
    assert cmd(e, b"AT") == b"[3] OK\r\n"
    assert cmd(e, b"ATS15=9") == b"[3] ERROR\r\n"  # not below NODECOUNT
    lines = cmd(e, b"ATI5").decode().split("\r\n")
    assert lines[15] == "[3] S15: NODEID=3"  # multipoint's param_print: a space after the colon
    assert len(lines[:-1]) == 19
    assert e.run_remote("RTI1,3").output == b"[3] 2.2\n"  # the target suffix is ignored
    # RTI5 goes back a line per packet, the whole table (tdm.c's packet_ati5_inject)
    result = e.run_remote("RTI5,3")
    assert result.per_line and len(result.output) > 252
    assert result.output.decode().splitlines()[18] == "[3] S18: NODECOUNT=4"
    assert not e.run_remote("RTI5X").per_line  # only RTI5 itself


def test_node_id_override() -> None:
    e = engine("multipoint", node_id=5)
    enter(e)
    assert cmd(e, b"AT") == b"[5] OK\r\n"


def test_constructor_errors() -> None:
    with pytest.raises(ConfigError, match="flavour"):
        ATEngine(SikParams("standard"), flavour="multipoint", ati6=str, ati7=str)
    with pytest.raises(ConfigError, match="board"):
        ATEngine(SikParams(), board="XYZ", ati6=str, ati7=str)


# -- robustness ---------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.binary(max_size=24), st.floats(0.0, 2.0)), max_size=30))
def test_any_input_is_handled(chunks: list[tuple[bytes, float]]) -> None:
    e = engine()
    t = 0.0
    for data, gap in chunks:
        t += gap
        out = e.feed(data, t)
        assert isinstance(out.to_host, bytes) and isinstance(out.to_air, bytes)
        assert out.remote_command is None or len(out.remote_command) <= 16
        assert set(out.to_air) <= set(data)
        if not e.in_command_mode:
            assert e.params.ram is not None
        e.poll(t + gap / 2)
        deadline = e.next_deadline()
        assert deadline is None or deadline >= t


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=40).filter(lambda b: b"\r" not in b))
def test_split_anywhere_same_as_whole(data: bytes) -> None:
    whole, split = engine(), engine()
    enter(whole)
    enter(split)
    a = whole.feed(data, 20.0)
    host, air = bytearray(), bytearray()
    for c in data:
        out = split.feed(bytes([c]), 20.0)
        host += out.to_host
        air += out.to_air
    assert (a.to_host, a.to_air) == (bytes(host), bytes(air))
    assert whole.in_command_mode == split.in_command_mode
