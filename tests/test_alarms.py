"""Alarm management, pure (swarm.core.station.alerts): one alarm per condition with its
count, latched until acknowledged, chattering, shelving with a timeout, priorities,
the flood limit, the on-delay and the battery's deadband; and the issue's target run
through the station core in virtual time: ten minutes of flapping links announce at
most 10 alarms to an operator who acknowledges each at once, none critical at start."""

from __future__ import annotations

import pytest
from test_gcs_station import connect, tm

from swarm.cli.bench.gcs_alarms import DEMO_FLAPPING, demo_in_virtual_time
from swarm.core.station.alerts import SHELVE_MAX_S, AlertBook, AlertConfig
from swarm.core.station.commands import CommandRefused
from swarm.core.station.core import StationCore
from swarm.core.wire.codes import SEPARATION_HOLD
from swarm.core.wire.message_types import AgentNotice, NoticeSource


def book(**kw: object) -> AlertBook:
    return AlertBook(cfg=AlertConfig(**kw))  # type: ignore[arg-type]


def test_a_flapping_condition_is_one_alarm_counted_and_announced_once() -> None:
    b = book()
    for i in range(20):
        b.raise_("link", 3, "critical", "agent3: link lost", 10.0 * i)
        b.clear("link", 3, 10.0 * i + 5)
    (a,) = b.alerts.values()
    assert (a.count, a.acked, len(a.announcements)) == (20, False, 1)
    assert a.raised == 0.0 and a.last == 190.0 and a.cleared == 195.0
    assert len(b.announced) == 1


def test_acknowledged_and_back_is_announced_again_until_it_chatters() -> None:
    b = book(chatter_count=3, chatter_window_s=600.0)  # EEMUA's: 3 a minute; ours: 2 in 10 min
    said = []
    for i in range(6):
        r = b.raise_("link", 3, "critical", "agent3: link lost", 60.0 * i)
        said.append(r.announced)
        assert r.alert is not None
        b.ack(r.alert.id)
        b.clear("link", 3, 60.0 * i + 10)
    (a,) = b.alerts.values()
    assert said == [True, True, True, False, False, False]
    assert a.quiet == "chattering" and a.count == 6 and a.id == 1
    # a whole window without an announcement: announced again when it comes back
    r = b.raise_("link", 3, "critical", "agent3: link lost", 120.0 + 600.0 + 1)
    assert r.announced and a.quiet is None


def test_chattering_does_not_hide_a_condition_that_gets_worse() -> None:
    b = book(chatter_count=1)
    r = b.raise_("battery", 3, "warning", "30 %", 0.0)
    assert r.alert is not None
    b.ack(r.alert.id)
    b.clear("battery", 3, 1.0)
    assert not b.raise_("battery", 3, "warning", "29 %", 2.0).announced
    assert b.raise_("battery", 3, "critical", "14 %", 3.0).announced
    assert not r.alert.acked


def test_a_shelved_alarm_is_quiet_until_its_time_is_up() -> None:
    b = book()
    r = b.raise_("link", 3, "warning", "losing 60 %", 0.0)
    assert r.alert is not None
    a = r.alert
    b.ack(a.id)
    b.shelve(a.id, 300.0, 10.0)
    assert a.quiet == "shelved" and a.shelved_until == 310.0 and not a.in_banner
    b.clear("link", 3, 20.0)
    assert not b.raise_("link", 3, "warning", "losing 60 %", 30.0).announced  # back, but shelved
    assert a.count == 2 and not a.acked
    assert b.next_deadline() == 310.0
    assert b.tick(309.0) == []
    assert [(r.alert, r.announced) for r in b.tick(310.0)] == [(a, True)]  # still active: announced again
    assert a.quiet is None and a.in_banner and a.announced == 310.0


def test_a_shelved_warning_that_turns_critical_is_announced() -> None:
    b = book()
    r = b.raise_("battery", 3, "warning", "25 %", 0.0)
    assert r.alert is not None
    b.shelve(r.alert.id, 600.0, 1.0)
    assert b.raise_("battery", 3, "critical", "14 %", 2.0).announced
    assert r.alert.quiet is None and r.alert.shelved_until is None


@pytest.mark.parametrize(
    ("alert_id", "seconds", "status"),
    [
        (1, -1, 400),
        (1, SHELVE_MAX_S + 1, 400),
        (1, float("nan"), 400),
        (1, float("inf"), 400),
        (1, "600", 400),
        (1, True, 400),
        (1, None, 400),
        ("1", 600, 400),
        (True, 600, 400),
        (99, 600, 404),
        (10**400, 600, 404),
    ],
)
def test_shelving_with_bad_arguments_is_a_clear_refusal(
    alert_id: object, seconds: object, status: int
) -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    core.handle(tm(3, battery=10), 0.1)
    with pytest.raises(CommandRefused) as exc:
        core.shelve_alert(alert_id, seconds, 1.0)
    assert exc.value.status == status and "\n" not in exc.value.reason and len(exc.value.reason) < 80
    (a,) = core.alerts.alerts.values()
    assert a.quiet is None
    row = core.shelve_alert(a.id, 600, 1.0)
    assert row["quiet"] == "shelved" and row["shelved_until"] == 601.0
    assert core.shelve_alert(a.id, 0, 2.0)["quiet"] is None
    assert any("shelved for 10 min" in e.text for e in core.events)


def test_advisories_are_listed_never_announced() -> None:
    b = book()
    a = b.once("command", 3, "advisory", "ARM -> agent3: REJECTED", 0.0)
    assert a.announced is None and not a.in_banner and len(b.announced) == 0
    assert [r["id"] for r in b.as_list()] == [a.id]


def test_a_flood_holds_warnings_but_never_a_critical() -> None:
    b = book(flood_limit=10, flood_window_s=600.0)
    said = [b.raise_("battery", i, "warning", f"agent{i} 25 %", float(i)).announced for i in range(1, 16)]
    assert said == [True] * 10 + [False] * 5
    held = [a for a in b.alerts.values() if a.quiet == "flood"]
    assert len(held) == 5 and b.held == 5 and b.rate(20.0)["flood"] is True
    assert b.raise_("vehicle_link", 1, "critical", "agent1: vehicle link lost", 21.0).announced
    assert b.rate(700.0) == {"announced": 0, "window_s": 600.0, "flood": False, "held": 5}


def test_a_separation_hold_shorter_than_the_on_delay_is_a_line_not_an_alarm() -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    core.take_events()

    def alive(until: float, t: float) -> None:
        while t <= until:
            core.handle(tm(3), t)
            core.tick(t)
            t += 0.5

    core.handle(AgentNotice(3, NoticeSource.AGENT, 4, SEPARATION_HOLD + " agent 4 (2.1 m)"), 1.0)
    alive(3.0, 1.0)
    core.handle(AgentNotice(3, NoticeSource.AGENT, 5, "separation restored: resuming"), 4.0)
    alive(10.0, 4.0)
    assert not core.alerts.alerts and core.alerts.filtered == 1
    assert [e.kind for e in core.take_events()] == ["agent", "agent"]
    alive(20.0, 10.5)
    core.handle(AgentNotice(3, NoticeSource.AGENT, 4, SEPARATION_HOLD + " agent 4 (1.1 m)"), 20.0)
    assert core.next_deadline() <= 20.0 + AlertConfig().on_delay_s
    alive(20.0 + AlertConfig().on_delay_s, 19.5)
    (a,) = core.alerts.alerts.values()
    assert a.kind == "separation" and a.in_banner
    assert any(e.kind == "alert" and "WARNING" in e.text for e in core.take_events())


def test_a_battery_wobbling_on_its_threshold_is_one_alarm() -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    for i, pct in enumerate((31, 30, 31, 32, 30, 33, 29, 31, 30)):
        core.handle(tm(3, battery=pct), 0.1 * (i + 1))
    (a,) = core.alerts.alerts.values()
    assert a.count == 1 and a.cleared is None
    core.handle(tm(3, battery=34), 2.0)  # above warning + deadband
    assert a.cleared is not None


def test_a_reason_not_to_arm_is_an_advisory_whatever_its_severity() -> None:
    core = StationCore()
    connect(core, 3, 0.0)
    for i in range(5):
        core.handle(AgentNotice(3, NoticeSource.AUTOPILOT, 2, "PreArm: GPS not healthy"), 30.0 * i)
    core.handle(AgentNotice(3, NoticeSource.AUTOPILOT, 2, "Crash: Disarming"), 200.0)
    rows = {a.text: a for a in core.alerts.alerts.values()}
    assert rows["agent3 (3): PreArm: GPS not healthy"].level == "advisory"
    assert rows["agent3 (3): PreArm: GPS not healthy"].count == 5
    assert rows["agent3 (3): Crash: Disarming"].level == "critical"


# -- the target, in virtual time --------------------------------------------------


@pytest.mark.parametrize("ack_after", [None, 5.0])
def test_ten_minutes_of_flapping_links_announce_at_most_ten_alarms(ack_after: float | None) -> None:
    said, core = demo_in_virtual_time(ack_after)
    disconnects = sum(e.kind == "disconnect" for e in core.events)
    assert disconnects >= 10  # the links did flap (the log keeps the newest 200 lines)
    assert 3 <= len(said) <= 10, said
    assert not [s for s in said if s[0] < 30.0 and s[1] == "critical"]  # no false critical at start
    link = [a for a in core.alerts.alerts.values() if a.kind == "link"]
    assert sorted(a.agent for a in link) == list(DEMO_FLAPPING)  # one alarm per flapping link
    assert all(a.count >= 9 for a in link)
