"""The station's state as it leaves the core: typed rows of the API's and the page's
JSON, and of what one station publishes to the others.

Theory of operation
-------------------
:meth:`~swarm.core.station.core.StationCore.snapshot` builds a :class:`Snapshot`: every
agent (:class:`AgentRow`), the events (:class:`EventRow`), the alerts
(:class:`AlertRow`), the swarms (:class:`SwarmRow`), the leader's task and slots, the
station radio. The server sends it as JSON, the page and the WebSocket deltas read it,
other stations receive its :class:`StationState` part. A fleet of several channels and
stations (:mod:`swarm.core.station.fleet`) tags each row with ``net`` (its channel)
or ``station`` (who hears it) and adds ``nets`` and ``stations``.

These are :class:`typing.TypedDict`s: at run time plain dicts (the JSON as it was),
for the type checker each key with its type. A key that only some rows carry is
``NotRequired``. What comes in from outside (a request body, another station's
state before :mod:`swarm.core.station.federation` cleaned it) is not one of these
until it has been checked. ``tests/test_station_rows.py`` holds the types to the rows
the code really builds (no postponed annotations here: the TypedDicts' required and
optional keys must be readable at run time).
"""

from typing import NotRequired, TypedDict


class EventRow(TypedDict):
    """One event: when (Unix time), its kind and one line."""

    t: float
    kind: str
    text: str
    net: NotRequired[str]
    station: NotRequired[str]


class AlertRow(TypedDict):
    """One alarm (:class:`~swarm.core.station.alerts.Alert`): one condition's record."""

    id: int
    kind: str
    agent: int
    level: str
    text: str
    raised: float
    last: float
    cleared: float | None
    acked: bool
    count: int
    announced: float | None
    quiet: str | None
    shelved_until: float | None
    net: NotRequired[str | None]
    station: NotRequired[str]
    station_alive: NotRequired[bool]


class DoingRow(TypedDict):
    """What an agent's last command is doing on its vehicle
    (:class:`~swarm.core.station.followup.Followup`)."""

    kind: str
    request: int
    state: str  # IN_PROGRESS, DONE, DID_NOT_HAPPEN, REPLACED
    text: str
    since: float


class AgentRow(TypedDict):
    """One agent as the station knows it (:class:`~swarm.core.station.model.AgentView`):
    unknown is None, never a default that reads as a fact."""

    id: int
    name: str
    connected: bool
    last_seen_s: float | None
    hb_s: float | None
    lat: float | None
    lon: float | None
    alt: float | None
    home_alt: float | None
    rel_alt: float | None
    climb: float | None
    gps_fix: int | None
    satellites: int | None
    home_dist: float | None
    ready: bool | None
    heading: float | None
    groundspeed: float | None
    mode: str | None
    armed: bool | None
    airborne: bool | None
    holding: bool | None
    control_lost: bool | None
    vehicle_link: bool | None
    battery: int | None
    rssi: int | None
    remrssi: int | None
    loss_pct: float | None
    phase: str | None
    leader: int
    pool: list[int]
    members: list[int]
    locked: bool
    home: NotRequired[list[float]]
    route: NotRequired[list[list[float]]]
    doing: NotRequired[DoingRow]
    trail: NotRequired[list[list[float]]]
    net: NotRequired[str | None]
    station: NotRequired[str]
    station_alive: NotRequired[bool]


class SwarmRow(TypedDict):
    """One swarm: its leader, its members and its colour on the page."""

    leader: int
    members: list[int]
    colour: NotRequired[int | None]
    station_colour: NotRequired[int | None]
    net: NotRequired[str | None]
    station: NotRequired[str]


class TaskRow(TypedDict):
    """A leader's FOLLOW task: heading in 0.5 degree steps, distances in metres."""

    leader: int
    heading: float
    back: float
    side: float


class RadioRow(TypedDict):
    """The station radio's RSSI, noise and margins, local and remote (SiK units)."""

    rssi: int
    noise: int
    margin: int
    remrssi: int
    remnoise: int
    remmargin: int


class SwarmsPart(TypedDict):
    """The swarms' part of a snapshot: each swarm, and each FOLLOW task and its slots but
    the station's leader's (those are ``task`` and ``slots``), by leader id as text."""

    swarms: list[SwarmRow]
    swarm_tasks: dict[str, TaskRow]
    swarm_slots: dict[str, list[list[int]] | None]


class StationState(TypedDict):
    """What one station publishes to the others (and takes from them, once cleaned)."""

    agents: list[AgentRow]
    events: list[EventRow]
    swarms: list[SwarmRow]
    alerts: list[AlertRow]


class StationInfo(TypedDict):
    """This station: its name, its system id and its link (radio or endpoints) in words."""

    name: str
    id: int
    link: str


class NetRow(TypedDict):
    """One channel of a station with several radios."""

    name: str
    station: str
    link: str


class StationRow(TypedDict):
    """One station of a federation: alive, and whether it is this one."""

    name: str
    alive: bool
    here: bool


class CapturedRadio(TypedDict):
    """The station radio's last RADIO_STATUS in a replayed capture, and when (capture time)."""

    rxerrors: int
    fixed: int
    rssi: int
    remrssi: int
    txbuf: int
    noise: int
    remnoise: int
    t: float


class ReplayStatus(TypedDict):
    """A replayed capture's place: playing or paused, speed, position, the radio's report."""

    playing: bool
    speed: float
    position_s: float
    duration_s: float
    time: float
    start: float
    seeks: int
    radio: CapturedRadio | None


class AlertAck(AlertRow):
    """An alert acknowledged at another station: forwarded there, not awaited."""

    forwarded: bool


class AlarmRate(TypedDict):
    """The station's alarm announcements in the last ``window_s`` (``flood``: at or over
    its limit: warnings are listed, not announced), and how many a flood held back."""

    announced: int
    window_s: float
    flood: bool
    held: int


class Snapshot(TypedDict):
    """The API's and the page's state object."""

    time: float
    leader: int
    agents: list[AgentRow]
    events: list[EventRow]
    alerts: list[AlertRow]
    alarm_rate: NotRequired[AlarmRate]
    radio: RadioRow | None
    task: TaskRow | None
    slots: list[list[int]] | None
    swarms: list[SwarmRow]
    swarm_tasks: dict[str, TaskRow]
    swarm_slots: dict[str, list[list[int]] | None]
    station: NotRequired[StationInfo]
    nets: NotRequired[list[NetRow]]
    stations: NotRequired[list[StationRow]]
    replay: NotRequired[ReplayStatus]


__all__ = [
    "AgentRow",
    "AlarmRate",
    "AlertAck",
    "AlertRow",
    "CapturedRadio",
    "DoingRow",
    "EventRow",
    "NetRow",
    "RadioRow",
    "ReplayStatus",
    "Snapshot",
    "StationInfo",
    "StationRow",
    "StationState",
    "SwarmRow",
    "SwarmsPart",
    "TaskRow",
]
