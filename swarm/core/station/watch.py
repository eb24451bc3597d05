"""What the ground station raises alerts for, and the lines it logs for them.

Theory of operation
-------------------
:class:`AlertWatch` is the station core's (:class:`swarm.core.station.core.StationCore`)
eye on its agents. The core calls it where it learns something, with ``now``:

* each Telemetry (:meth:`AlertWatch.telemetry`): the link's record
  (:class:`~swarm.core.station.alerts.LinkHealth`), the battery against the warning
  and critical thresholds (raised when crossed, cleared above the warning), the
  measured loss with hysteresis (raised at ``loss_alert`` %, cleared below
  ``loss_clear`` %);
* the vehicle link lost or back (FLAG_FC_OK), an agent disconnected or connected
  (its silence beyond what its link's record allows: a ``link`` alert, critical);
* an :class:`~swarm.core.wire.message_types.AgentNotice`: an autopilot STATUSTEXT (an
  alarm: ``critical`` at severity CRITICAL or worse, else ``warning``; ``advisory`` for
  the reasons not to arm, "PreArm: ..." and the like, which ArduPilot repeats at
  CRITICAL while on the ground) or one of the agent's own events
  (a line in the log; a separation hold that lasts the on-delay is also an alarm),
  every one in the log with its repeats;
* each finished command whose result is a refusal or no answer (an advisory: its
  sender sees the result);
* time (:meth:`AlertWatch.tick`): on-delays and shelves that ran out.

Notices are bounded here too, whatever the agent's gate did: a bucket of
``NOTICE_BURST`` per agent refilled one per ``NOTICE_EVERY_S``; what is over is
counted (``notices_dropped``), not logged, so a hostile agent cannot wash the log out.

Every alarm occurrence (new, back, or worse) is also a line in the station's event log
(kind ``alert``, saying when it was not announced and why; a disconnect, a vehicle link
lost or a command's result already is one: it is not logged twice), so the log holds
the whole story and the banner what needs a look.
Pure: no I/O, no clock.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from swarm.core.station.alerts import Alert, AlertBook, AlertConfig, battery_level
from swarm.core.wire.codes import CRITICAL, SEPARATION_HOLD, SEVERITY_NAMES, one_line
from swarm.core.wire.message_types import AgentNotice, NoticeSource

if TYPE_CHECKING:
    from swarm.core.station.commands import Request
    from swarm.core.station.model import AgentView

NOTICE_BURST = 5
NOTICE_EVERY_S = 2.0
#: command results that are not a refusal (or are not over yet)
_NOT_REFUSED = ("ACCEPTED", "CARRIED_OUT", "IN_PROGRESS", None)


#: autopilot texts that tell why it will not arm: advisories (the vehicle is on the
#: ground; ArduPilot repeats them at CRITICAL severity every 30 s while disarmed)
ARMING_TEXTS = ("PreArm:", "Arm:", "Preflight Fail:", "Arming denied")


def _text_level(severity: int, text: str) -> str:
    """An autopilot text's priority: CRITICAL or worse critical, else a warning (the
    agent forwards WARNING and worse: "Radio Failsafe", "GPS Glitch" are WARNINGs); a
    reason not to arm always an advisory."""
    if text.startswith(ARMING_TEXTS):
        return "advisory"
    return "critical" if severity <= CRITICAL else "warning"


class AlertWatch:
    """Alerts from what the station core learns (module docstring). ``label`` names an
    agent for a line; ``event(now, kind, text)`` logs one."""

    def __init__(
        self,
        cfg: AlertConfig,
        book: AlertBook,
        label: Callable[[int], str],
        event: Callable[[float, str, str], None],
    ) -> None:
        self.cfg = cfg
        self.book = book
        self._label = label
        self._event = event
        self._buckets: dict[int, tuple[float, float]] = {}  # agent -> (tokens, when)
        self.notices_dropped = 0

    def _raise(
        self, kind: str, agent: int, level: str, text: str, now: float, *, delay: bool = False
    ) -> None:
        r = self.book.raise_(kind, agent, level, text, now, delay=delay)
        if r.occurred and r.alert is not None:  # new, back or worse: a line in the log
            self._log(r.alert, r.announced, now)

    def _log(self, a: Alert, announced: bool, now: float) -> None:
        why = "" if announced else f" (not announced: {a.quiet or 'still unacknowledged'}, {a.count} times)"
        self._event(now, "alert", f"{a.level.upper()}: {a.text}{why}")

    def tick(self, now: float) -> None:
        """On-delays and shelves that ran out (:meth:`AlertBook.tick`): their lines."""
        for r in self.book.tick(now):
            if r.alert is not None:
                self._log(r.alert, r.announced, now)

    def _clear(self, kind: str, agent: int, text: str, now: float) -> None:
        if self.book.clear(kind, agent, now) is not None:
            self._event(now, "alert", text)

    def telemetry(self, a: AgentView, now: float, base_heartbeats: float, *, link: bool = True) -> None:
        """``link``: judge the link too (not in a replay: its arrivals are the capture's)."""
        cfg = self.cfg
        if link:
            a.link.arrival(now, a.hb_interval, cfg, base_heartbeats)
        who = self._label(a.id)
        level = battery_level(a.battery, cfg)
        if level is not None:
            limit = cfg.battery_critical if level == "critical" else cfg.battery_warning
            self._raise("battery", a.id, level, f"{who}: battery {a.battery} % (at or below {limit} %)", now)
        elif a.battery is not None and a.battery > cfg.battery_warning + cfg.battery_deadband:
            self._clear("battery", a.id, f"{who}: battery {a.battery} %, above the warning", now)
        loss = a.link.loss
        if loss is None:
            return
        pct = 100.0 * loss
        if pct >= cfg.loss_alert and not a.link.lossy:
            a.link.lossy = True
            self._raise("link", a.id, "warning", f"{who}: link losing {pct:.0f} % of Telemetry", now)
        elif pct < cfg.loss_clear and a.link.lossy:
            a.link.lossy = False
            self._clear("link", a.id, f"{who}: link loss down to {pct:.0f} %", now)

    def vehicle_link(self, a: AgentView, up: bool, now: float) -> None:
        who = self._label(a.id)
        if up:
            self.book.clear("vehicle_link", a.id, now)
        else:
            self.book.raise_("vehicle_link", a.id, "critical", f"{who}: vehicle link lost", now)

    def disconnected(self, a: AgentView, silent: float, now: float) -> None:
        """The silence is its own alert: the loss record starts again at the reconnection."""
        a.link.reset()
        text = f"{self._label(a.id)}: link lost (silent for {silent:.1f} s)"
        self.book.raise_("link", a.id, "critical", text, now)  # the disconnect is its line

    def connected(self, a: AgentView, now: float) -> None:
        if self.book.is_open("link", a.id) and not a.link.lossy:
            self.book.clear("link", a.id, now)

    def notice(self, msg: AgentNotice, now: float) -> None:
        """An agent's notice: a line in the log, an alert for an autopilot text or a
        separation hold. Its text is made one line again (it came over the air)."""
        tokens, t = self._buckets.get(msg.sender, (float(NOTICE_BURST), now))
        tokens = min(float(NOTICE_BURST), tokens + max(0.0, now - t) / NOTICE_EVERY_S)
        if tokens < 1.0:
            self.notices_dropped += 1
            self._buckets[msg.sender] = (tokens, now)
            return
        self._buckets[msg.sender] = (tokens - 1.0, now)
        who = self._label(msg.sender)
        text = one_line(msg.text)
        more = f" (+{msg.repeats} more)" if msg.repeats else ""
        sev = SEVERITY_NAMES[msg.severity]
        if msg.source == NoticeSource.AUTOPILOT:
            level = _text_level(msg.severity, text)
            self._event(now, "autopilot", f"{who}: {sev.upper()} {text}{more}")
            self.book.once("statustext", msg.sender, level, f"{who}: {text}", now, 1 + msg.repeats)
            return
        self._event(now, "agent", f"{who}: {text}{more}")
        if text.startswith(SEPARATION_HOLD):
            self._raise("separation", msg.sender, "warning", f"{who}: {text}", now, delay=True)
        elif text.startswith("separation restored"):
            self.book.clear("separation", msg.sender, now)

    def finished(self, req: Request, now: float) -> None:
        """A command finished: an alert for each addressee that refused or never answered."""
        for p in req.pending:
            if p.result in _NOT_REFUSED:
                continue
            why = f" ({p.reason})" if p.reason else ""
            text = f"{p.msg.kind.name} -> {self._label(p.agent)}: {p.result}{why}"
            self.book.once("command", p.agent, "advisory", text, now)  # its sender sees the result


__all__ = ["AlertWatch"]
