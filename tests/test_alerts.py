"""Alerts and link health, pure: the agent's notice gate (hostile autopilot text,
floods), the node forwarding notices to its stations, the station's link judgement
(a 20 % lossy link never flaps over hours of virtual time; real silence disconnects),
battery and loss thresholds, the alert book and acknowledgements (hostile ids), and
the simulator's fast battery drain."""

from __future__ import annotations

import math
import random

import pytest
from test_gcs_station import POSE, connect, tm

from firmware_bridge.sim.autopilot import BATTERY_CRITICAL, BATTERY_LOW, Autopilot
from swarm.core.agent.node import AgentNode, AutopilotText, PositionFix, Send
from swarm.core.agent.notices import NoticeConfig, NoticeGate
from swarm.core.election.profiles import profile_by_name
from swarm.core.station.alerts import AlertConfig, LinkHealth
from swarm.core.station.commands import CommandRefused, parse_command
from swarm.core.station.core import StationCore
from swarm.core.station.model import StationConfig
from swarm.core.station.rows import AlertRow
from swarm.core.wire.codes import FLAG_FC_OK, SEPARATION_HOLD, one_line
from swarm.core.wire.message_types import (
    NOTICE_MAX,
    AckResult,
    AgentNotice,
    CommandAck,
    GSAdvertize,
    GSConnect,
    NoticeSource,
)
from swarm.core.wire.messages import decode, encode
from swarm.errors import DecodeError, MessageError

AUTO, AGENT = NoticeSource.AUTOPILOT, NoticeSource.AGENT

# -- the agent's gate -------------------------------------------------------------------

HOSTILE = [
    "PreArm: \x1b[31mGPS\x1b[0m\r\nfake line",
    "\x00\x00Battery\x00low\x00",
    "\u202eevil\u2066 bidi \u200b",  # bidi overrides and zero-width: format characters
    "x" * 5000,
    "é" * 100,  # cut on a whole character
    "\t\n\r\x7f",
]


@pytest.mark.parametrize("text", HOSTILE)
def test_a_hostile_autopilot_text_becomes_one_printable_bounded_line(text: str) -> None:
    line = one_line(text)
    assert line.isprintable() and "\n" not in line and "\x1b" not in line
    assert len(line.encode()) <= NOTICE_MAX
    assert line == line.strip() and "  " not in line
    if line:  # it crosses the air and decodes to the same
        msg = AgentNotice(3, AUTO, 4, line)
        assert decode(encode(msg)) == msg


def test_a_notice_that_is_not_one_printable_line_is_refused_both_ways() -> None:
    with pytest.raises(MessageError):
        AgentNotice(3, AUTO, 4, "two\nlines")
    with pytest.raises(MessageError):
        AgentNotice(3, AUTO, 9, "x")
    good = encode(AgentNotice(3, AUTO, 4, "ab"))
    for bad in (good[:-1] + b"\n", good[:3] + b"\x08" + good[4:], good + b"x", good[:-3]):
        with pytest.raises(DecodeError):
            decode(bad)


def test_a_notice_costs_at_most_70_bytes_and_one_every_4_s_in_the_long_run() -> None:
    longest = AgentNotice(250, AUTO, 0, one_line("é" * 200), 255)
    assert len(encode(longest)) <= 70  # + 17 of TUNNEL framing, + 13 signed: 100 bytes on air
    cfg = NoticeConfig()
    assert cfg.interval_s >= 4.0 and cfg.burst <= 2  # at most 25 bytes/s per agent


def test_autopilot_texts_below_warning_stay_on_the_agent() -> None:
    g = NoticeGate()
    assert not g.offer(AUTO, 6, "EKF3 IMU0 is using GPS", 0.0)  # INFO
    assert not g.offer(AUTO, 5, "Mode change", 0.0)  # NOTICE
    assert g.offer(AUTO, 4, "PreArm: GPS not healthy", 0.0)  # WARNING
    assert g.offer(AGENT, 6, "took off: holding", 0.0)  # the agent's own events always
    assert [n.text for n in g.take(0.0)] == ["PreArm: GPS not healthy", "took off: holding"]
    assert g.counters.below_severity == 2


def test_a_repeated_text_crosses_once_per_dedup_window_with_its_count() -> None:
    g = NoticeGate(NoticeConfig(dedup_s=30.0))
    sent = []
    t = 0.0
    while t < 120.0:  # 10 Hz for two minutes: 1200 copies
        g.offer(AUTO, 4, "PreArm: Compass not calibrated", t)
        sent += [(round(t, 1), n.repeats) for n in g.take(t)]
        t = round(t + 0.1, 1)
    assert [s[0] for s in sent] == [0.0, 30.0, 60.0, 90.0]
    assert sent[0][1] == 0 and all(r == 255 for _, r in sent[1:])  # counted (capped at 255)
    assert g.counters.sent == 4 and g.waiting == 1 and g.counters.merged == 1200 - 5


def test_a_flood_of_distinct_texts_is_rate_limited_bounded_and_severe_first() -> None:
    cfg = NoticeConfig(interval_s=4.0, burst=2, pending=8)
    g = NoticeGate(cfg)
    sent = []
    for i in range(6000):  # 100 distinct lines a second for a minute
        t = i / 100
        g.offer(AUTO, 2 if i % 500 == 0 else 4, f"flood {i}", t)
        assert g.waiting <= cfg.pending
        sent += g.take(t)
    assert len(sent) <= cfg.burst + 60 / cfg.interval_s
    assert sum(1 for n in sent if n.severity == 2) == 6000 // 500  # every critical one went, first
    assert g.counters.dropped > 5000


def test_the_gate_says_when_to_come_back() -> None:
    g = NoticeGate(NoticeConfig(interval_s=4.0, burst=1))
    assert g.next_deadline() == math.inf
    g.offer(AUTO, 4, "one", 0.0)
    g.offer(AUTO, 4, "two", 0.0)
    assert len(g.take(0.0)) == 1
    assert g.next_deadline() == pytest.approx(4.0)
    assert g.take(3.9) == [] and [n.text for n in g.take(4.0)] == ["two"]


# -- the node forwards them ----------------------------------------------------------------


def node_with_station() -> AgentNode:
    node = AgentNode(3, "agent3", profile_by_name("paper", 0.2368), has_fc=True)
    node.start(0.0)
    node.handle(GSAdvertize(255, "gcs"), 0.0)
    node.handle(GSConnect(255, 7), 0.0)
    assert node.gs.connected == [255]
    return node


def notices(outs: list[object]) -> list[AgentNotice]:
    return [o.msg for o in outs if isinstance(o, Send) and isinstance(o.msg, AgentNotice) and o.to == 255]


def test_the_node_forwards_warnings_and_its_own_events_to_its_station() -> None:
    node = node_with_station()
    node.handle(AutopilotText(4, "Battery 1 is low\x00\x00"), 1.0)
    node.handle(AutopilotText(6, "an INFO line"), 1.0)
    node.handle(PositionFix(False, "no GPS fix"), 1.0)
    got = notices(node.tick(1.0))
    assert [(n.source, n.severity, n.text) for n in got] == [
        (AUTO, 4, "Battery 1 is low"),
        (AGENT, 5, "waiting for position (no GPS fix)"),
    ]


def test_a_statustext_in_bytes_with_bad_utf8_is_forwarded_as_a_clean_line() -> None:
    node = node_with_station()
    node.handle(AutopilotText(3, b"EKF3 \xff lane\x00\x00"), 1.0)
    (n,) = notices(node.tick(1.0))
    assert n.text == "EKF3 \ufffd lane" and n.severity == 3


def test_without_a_station_notices_wait_bounded() -> None:
    node = AgentNode(3, "agent3", profile_by_name("paper", 0.2368), has_fc=True)
    node.start(0.0)
    for i in range(100):
        node.handle(AutopilotText(4, f"text {i}"), i * 0.1)
        assert not notices(node.tick(i * 0.1))
    assert node.notices.waiting <= NoticeConfig().pending


# -- the station's link judgement ----------------------------------------------------------


def run_lossy(loss: float, minutes: float, seed: int) -> tuple[StationCore, list[str]]:
    """An agent at 1 Hz whose Telemetry is lost at ``loss``, for ``minutes`` of virtual time."""
    core = StationCore()
    connect(core, 3, 0.0, hb_ms=1000)
    core.take_events()
    rng = random.Random(seed)
    drops = []
    t, next_tm = 0.0, 0.0
    while t < minutes * 60:
        if t >= next_tm:
            next_tm += 1.0
            if rng.random() >= loss:
                core.handle(tm(3), t + rng.uniform(0.0, 0.08))  # and some jitter
        core.tick(t)
        drops += [e.text for e in core.take_events() if e.kind == "disconnect"]
        t = round(t + 0.1, 1)
    return core, drops


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_agent_losing_20_percent_never_flaps_over_an_hour(seed: int) -> None:
    core, drops = run_lossy(0.20, 60, seed)
    assert drops == []
    a = core.agents[3]
    assert a.connected and 15.0 <= a.as_dict(0.0)["loss_pct"] <= 25.0
    assert not core.alerts.is_open("link", 3)  # 20 % is below the 50 % link alert


def test_the_old_rule_flapped_at_20_percent() -> None:
    """What the measured judgement fixes: three missed heartbeats at 20 % happen about
    every two minutes (0.2**3 a second)."""
    rng = random.Random(1)
    runs, run = 0, 0
    for _ in range(3600):
        run = run + 1 if rng.random() < 0.2 else 0
        runs += run == 3
    assert runs > 10


def test_real_silence_disconnects_clean_and_lossy_agents_within_ten_heartbeats() -> None:
    for loss, limit in ((0.0, 3.2), (0.2, 10.2)):
        core, drops = run_lossy(loss, 5, seed=4)
        assert drops == []
        last = core.agents[3].last_telemetry
        t = 300.0
        while core.agents[3].connected:
            t = round(t + 0.1, 1)
            core.tick(t)
        assert t - last <= limit, (loss, t - last)
        assert core.alerts.is_open("link", 3)  # a link alert, critical, until it is back


def test_link_health_loss_and_silence_from_arrivals() -> None:
    cfg = AlertConfig()
    h = LinkHealth()
    for i in range(4):
        h.arrival(float(i), 1.0, cfg, 3)
    assert h.loss is None and h.silence_s is None  # too short a record: the base timeout
    for i in range(4, 200):
        h.arrival(float(i), 1.0, cfg, 3)
    assert h.loss == 0.0 and h.silence_s == 3.0
    h2 = LinkHealth()
    for i in range(200):
        if i % 2:
            h2.arrival(float(i), 1.0, cfg, 3)
    assert h2.loss == pytest.approx(0.5, abs=0.02) and h2.silence_s == 10.0


def test_the_link_alert_has_hysteresis_on_the_measured_loss() -> None:
    core = StationCore()
    connect(core, 3, 0.0, hb_ms=1000)
    # which of every five heartbeats arrive: 0 %, 60 %, 40 %, then 0 % lost
    t, phases = 0.0, [(200, "xxxxx"), (200, "x-x--"), (200, "x-xx-"), (200, "xxxxx")]
    states = []
    for secs, pattern in phases:
        for i in range(secs):
            if pattern[i % 5] == "x":
                core.handle(tm(3), t)
            core.tick(t)
            t += 1.0
        states.append(core.alerts.is_open("link", 3))
    assert states == [False, True, True, False]
    lines = [e.text for e in core.events if e.kind == "alert"]
    assert sum("link losing" in x for x in lines) == 1 and sum("link loss down" in x for x in lines) == 1


# -- thresholds and the alert book -----------------------------------------------------------


def test_battery_warning_and_critical_thresholds() -> None:
    core = StationCore(config=StationConfig(alerts=AlertConfig(battery_warning=30, battery_critical=15)))
    connect(core, 3, 0.0)
    levels = []
    for i, pct in enumerate((80, 31, 30, 22, 15, 10, 255, 12)):
        core.handle(tm(3, battery=pct), 0.1 * i)
        open_ = [a for a in core.alerts.alerts.values() if a.kind == "battery" and a.cleared is None]
        levels.append(open_[0].level if open_ else None)
    assert levels == [None, None, "warning", "warning", "critical", "critical", "critical", "critical"]
    (a,) = [a for a in core.alerts.alerts.values() if a.kind == "battery"]
    core.ack_alert(a.id)
    core.handle(tm(3, battery=90), 2.0)  # recharged (swapped): cleared, stays acknowledged
    assert a.cleared is not None and a.acked
    core.handle(tm(3, battery=25), 3.0)  # low again: the same alarm, back and unacknowledged
    assert [(x.id, x.acked, x.count) for x in core.alerts.alerts.values() if x.kind == "battery"] == [
        (a.id, False, 2)
    ]


def test_a_warning_acknowledged_and_turned_critical_is_shown_again() -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    core.handle(tm(3, battery=25), 0.1)
    (a,) = core.alerts.alerts.values()
    core.ack_alert(a.id)
    core.handle(tm(3, battery=24), 0.2)
    assert a.acked
    core.handle(tm(3, battery=14), 0.3)
    assert not a.acked and a.level == "critical"


@pytest.mark.parametrize(
    "kwargs",
    [
        {"battery_warning": 10, "battery_critical": 20},
        {"battery_warning": 101},
        {"battery_critical": -1},
        {"battery_warning": 30.5},
        {"loss_alert": 20.0},
        {"loss_alert": math.nan},
        {"keep": 0},
    ],
)
def test_bad_alert_settings_are_refused(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        AlertConfig(**kwargs)  # type: ignore[arg-type]


def test_vehicle_link_loss_is_a_critical_alert_cleared_when_back() -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    core.handle(tm(3, flags=FLAG_FC_OK), 0.1)
    core.handle(tm(3, flags=0), 0.2)
    assert core.alerts.is_open("vehicle_link", 3)
    core.handle(tm(3, flags=FLAG_FC_OK), 0.3)
    assert not core.alerts.is_open("vehicle_link", 3)
    (a,) = core.alerts.alerts.values()
    assert a.level == "critical" and a.cleared is not None and not a.acked


def test_notices_become_log_lines_and_alerts() -> None:
    core = StationCore(wall_offset=1000.0)
    connect(core, 3, 0.0)
    core.take_events()
    core.handle(AgentNotice(3, AUTO, 4, "Battery 1 is low", 3), 1.0)
    core.handle(AgentNotice(3, AUTO, 2, "EKF variance"), 1.1)
    core.handle(AgentNotice(3, AGENT, 6, "took off: holding"), 1.2)
    core.handle(AgentNotice(3, AGENT, 4, SEPARATION_HOLD + " agent 4 (2.1 m)"), 1.3)
    lines = [(e.kind, e.text) for e in core.take_events()]
    assert lines[:3] == [
        ("autopilot", "agent3 (3): WARNING Battery 1 is low (+3 more)"),
        ("autopilot", "agent3 (3): CRITICAL EKF variance"),
        ("agent", "agent3 (3): took off: holding"),
    ]
    alerts = {a.kind + ":" + a.level: a for a in core.alerts.alerts.values()}
    # the separation hold is no alarm before its on-delay
    assert set(alerts) == {"statustext:warning", "statustext:critical"}
    assert alerts["statustext:warning"].count == 4
    assert alerts["statustext:warning"].raised == pytest.approx(1001.0)
    core.tick(1.3 + AlertConfig().on_delay_s)
    assert core.alerts.is_open("separation", 3)
    core.handle(AgentNotice(3, AGENT, 5, "separation restored: resuming"), 9.0)
    assert not core.alerts.is_open("separation", 3)


def test_a_hostile_agent_cannot_wash_out_the_log_with_notices() -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    connect(core, 4, 0.0)
    core.take_events()
    for i in range(1000):
        core.handle(AgentNotice(3, AUTO, 0, f"spam {i}"), i * 0.01)  # 100 a second for 10 s
    core.handle(AgentNotice(4, AUTO, 4, "honest warning"), 10.0)
    texts = [e.text for e in core.take_events()]
    assert len(texts) <= 5 + 10 / 2 + 2
    assert texts[-1] == "agent4 (4): WARNING honest warning"
    assert core.watch.notices_dropped > 900
    assert len(core.alerts.alerts) <= AlertConfig().keep


def test_a_refused_command_is_an_alert() -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    req, outs = core.submit(parse_command({"kind": "arm", "target": 3}), 1.0)
    seq = outs[0].msg.seq
    core.handle(CommandAck(3, seq, AckResult.REJECTED, "Arm: Battery low"), 1.2)
    assert [r.id for r in core.take_finished()] == [req.id]
    (a,) = [a for a in core.alerts.alerts.values() if a.kind == "command"]
    assert a.text == "ARM -> agent3 (3): REJECTED (Arm: Battery low)" and a.level == "advisory"
    assert a.announced is None  # its sender sees the result: never in the banner


@pytest.mark.parametrize(
    ("alert_id", "status"),
    [(None, 400), ("1", 400), (True, 400), (1.0, 400), ([1], 400), (99, 404), (-1, 404), (10**400, 404)],
)
def test_acknowledging_a_bad_id_is_a_clear_refusal(alert_id: object, status: int) -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    core.handle(tm(3, battery=10), 0.1)
    with pytest.raises(CommandRefused) as exc:
        core.ack_alert(alert_id)
    assert exc.value.status == status and "\n" not in exc.value.reason and len(exc.value.reason) < 80
    (a,) = core.alerts.alerts.values()
    assert core.ack_alert(a.id)["acked"] is True and a.acked


def test_the_state_carries_open_alerts_and_only_the_last_acknowledged() -> None:
    core = StationCore()
    for i in range(30):
        core.handle(AgentNotice(3, AUTO, 4, f"text {i}"), 10.0 * i)  # slow enough to pass the bucket
    ids = [a.id for a in core.alerts.alerts.values()]
    for i in ids[:25]:
        core.ack_alert(i)
    shown = core.snapshot(300.0)["alerts"]
    assert [a["id"] for a in shown] == ids[15:]  # 10 acknowledged, then the 5 still open
    assert [a["acked"] for a in shown] == [True] * 10 + [False] * 5


def test_the_state_carries_the_alerts() -> None:
    import json

    core = StationCore()
    connect(core, 3, 0.0)
    core.handle(tm(3, battery=10), 0.1)
    snap = core.snapshot(0.2)
    assert json.loads(core.snapshot_json(0.2, {"name": "gcs"}))["alerts"] == snap["alerts"]
    (a,) = snap["alerts"]
    assert a["kind"] == "battery" and a["level"] == "critical" and a["acked"] is False
    assert set(a) == set(AlertRow.__annotations__) - {"net", "station", "station_alive"}
    assert snap["alarm_rate"] == {"announced": 1, "window_s": 600.0, "flood": False, "held": 0}
    assert snap["agents"][0]["loss_pct"] is None  # not enough record yet
    assert POSE is not None


def test_the_station_radio_margins_are_shown_while_fresh() -> None:
    core = StationCore()
    assert core.snapshot(0.0)["radio"] is None
    core.observe_radio(180, 60, 170, 75, 10.0)
    assert core.snapshot(12.0)["radio"] == {
        "rssi": 180,
        "noise": 60,
        "margin": 120,
        "remrssi": 170,
        "remnoise": 75,
        "remmargin": 95,
    }
    assert core.snapshot(15.1)["radio"] is None  # stale: not shown as if current


def test_a_replay_shows_battery_alerts_but_judges_no_link() -> None:
    core = StationCore(passive=True)
    core.learn(3, "agent3", 0.0)
    for i in range(30):
        core.handle(tm(3, battery=10), float(i))
    assert [a.kind for a in core.alerts.alerts.values()] == ["battery"]
    assert core.agents[3].link.loss is None


# -- the simulator's battery ------------------------------------------------------------------


def texts_of(msgs: list[object]) -> list[tuple[int, str]]:
    return [(m.severity, m.text) for m in msgs if m.get_type() == "STATUSTEXT"]  # type: ignore[attr-defined]


def test_the_simulator_drains_fast_and_warns_once_per_level() -> None:
    ap = Autopilot("px4", 1, (47.0, 8.0, 500.0), battery_drain=600.0)  # 10 % a second
    got: list[tuple[int, str]] = []
    t = 0.0
    while t < 12.0:
        t = round(t + 0.02, 2)
        got += texts_of(ap.tick(t))
    assert got == [(4, "Low battery level! Return advised"), (2, "Critical battery level! Land now")]
    assert ap.battery == 0.0
    assert BATTERY_CRITICAL < BATTERY_LOW
    with pytest.raises(ValueError):
        Autopilot("px4", 1, (47.0, 8.0, 500.0), battery_drain=-1.0)
    idle = Autopilot("ardupilot", 1, (47.0, 8.0, 500.0))
    idle.tick(60.0)
    assert idle.battery == 100.0  # no drain asked: a disarmed vehicle keeps its battery
