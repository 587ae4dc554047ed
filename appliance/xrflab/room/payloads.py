"""Every MQTT payload of the room, both directions: one pydantic model each, with bounds.

This module is the payloads' one definition (topics.py names the topics; docs/educators/room.md
and docs/developers/security.md describe both). A sender builds its model (``Model.make(...)``:
a field the model does not declare is an error there, so a sender cannot drift from the contract
silently) and publishes ``model.wire()``; a receiver parses with ``parse`` and never looks at
the raw JSON.

Receiving is strict: the JSON types must be the declared ones (no "5" for 5, no 9e18 for an
integer), strings, lists and numbers are bounded, and a payload is at most ``BENCH_MAX_BYTES``
(from a bench) or ``ROOM_MAX_BYTES`` (from the room) long before it is even parsed. Whatever does
not fit raises ``Malformed``: the receiver drops it, counts it and logs it (``Drops``: one line per
source every ``Drops.EVERY_S``, so a flood cannot flood the log), and carries on. Fields a model
does not declare are ignored on receipt (a newer or older peer may send more; nothing undeclared
is ever kept or used).

A bench's payloads are not trusted for anything but what it says about itself on its own tile:
its identity is its broker login (the ACL puts it in the topic) and its address is the one
recorded at enrolment (service.py), never a field here.
"""

from __future__ import annotations

import logging
import re
import time
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from ..grading.results import STATUSES as GRADE_STATUSES
from ..grading.scenario import MAX_BYTES as SCENARIO_MAX_BYTES
from ..grading.scenario import MAX_ITEMS as SCENARIO_MAX_ITEMS
from ..projects.assignments import ID_RE as ASSIGNMENT_ID_RE
from ..projects.assignments import LIMITS as ASSIGNMENT_LIMITS
from ..server.security.roles import USERNAME_RE, Role
from ..server.settings import Settings
from .topics import NAME_RE

log = logging.getLogger(__name__)

BENCH_MAX_BYTES = 64 << 10  # a bench's status, event, reply or online message
GRADES_MAX_BYTES = 512 << 10  # a bench's grading table of one assignment (xrf/bench/<name>/grades)
MAX_GRADE_ROWS = 1000  # projects in one bench's grading table (the rest: `left_out`)
ROOM_MAX_BYTES = 8 << 20  # the room's class list and assignments (the largest: the class list)
# mosquitto disconnects a client that sends a larger packet (broker.py: max_packet_size)
BROKER_MAX_PACKET = ROOM_MAX_BYTES + (64 << 10)
INLINE_MAX = 128 << 10  # an assignment's archive inside its message (MQTT could carry more; it is retained)
CLASS_LIST_MAX = 5000  # accounts in one class list
MAX_ALARMS = 5  # the latest alarms a status carries
MAX_ASSIGNMENTS = 500  # assignment ids a status lists
SAFE_INT = 2**53  # integers a browser's JSON reads exactly

# ---- bounded types --------------------------------------------------------------------------

Count = Annotated[int, Field(ge=0, le=SAFE_INT)]
# Unix time in s: a finite number up to the year 5138 (no NaN, no infinity, nothing negative)
Clock = Annotated[float, Field(ge=0, le=1e11, allow_inf_nan=False)]
Text32 = Annotated[str, Field(max_length=32)]
Text64 = Annotated[str, Field(max_length=64)]
Text128 = Annotated[str, Field(max_length=128)]
Text300 = Annotated[str, Field(max_length=300)]
Text500 = Annotated[str, Field(max_length=500)]
Kind = Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]{0,31}$")]  # an alarm's kind, a verdict
BenchName = Annotated[str, Field(pattern=NAME_RE.pattern)]
AssignmentId = Annotated[str, Field(pattern=ASSIGNMENT_ID_RE.pattern)]
CommandId = Annotated[str, Field(pattern=r"^[0-9a-f]{1,32}$")]  # secrets.token_hex(8) in the room
# (ms since the epoch of the appliance's start, publisher.next_boot; seq counts up within it)
Boot = Annotated[int, Field(ge=0, le=SAFE_INT)]


class Malformed(ValueError):
    """A payload that does not fit its model (or its size): dropped by the receiver."""


class _Payload(BaseModel):
    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    @classmethod
    def make(cls, **fields: Any) -> Any:
        """The sender's way: every field must be declared (a typo or a new field fails here, with
        its name), values are checked against the same bounds the receiver applies."""
        unknown = set(fields) - set(cls.model_fields)
        if unknown:
            raise TypeError(f"{cls.__name__} has no field(s) {', '.join(sorted(unknown))} (payloads.py)")
        return cls.model_validate(fields, strict=False)

    def wire(self) -> bytes:
        return self.model_dump_json(exclude_none=True).encode()


M = TypeVar("M")


def parse(adapter: TypeAdapter[M], payload: bytes | bytearray, limit: int) -> M:
    """`payload` as the model of `adapter`, or Malformed (with a short reason: a log line)."""
    if len(payload) > limit:
        raise Malformed(f"{len(payload)} bytes (at most {limit})")
    try:
        return adapter.validate_json(bytes(payload), strict=True)
    except ValidationError as exc:
        first = exc.errors(include_url=False, include_input=False)[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or "payload"
        raise Malformed(f"{where}: {first.get('msg', 'invalid')}"[:200]) from None


class Drops:
    """Dropped payloads of one receiver: counted per source, logged at most once per source every
    EVERY_S with the number dropped since (a bench sending garbage cannot flood the log)."""

    EVERY_S = 10.0
    MAX_SOURCES = 1000

    def __init__(self, who: str) -> None:
        self.who = who
        self.counts: dict[str, int] = {}
        self._logged: dict[str, tuple[float, int]] = {}

    def drop(self, source: str, topic: str, why: str) -> None:
        source = source[:64]
        if source not in self.counts and len(self.counts) >= self.MAX_SOURCES:
            source = "(others)"
        n = self.counts[source] = self.counts.get(source, 0) + 1
        now = time.monotonic()
        last_t, last_n = self._logged.get(source, (-self.EVERY_S, 0))
        if now - last_t >= self.EVERY_S:
            more = f" ({n - last_n - 1} more dropped since the last line)" if n - last_n > 1 else ""
            log.warning("%s: dropped a message on %s from %s: %s%s", self.who, topic[:100], source, why[:200], more)
            self._logged[source] = (now, n)


# ---- bench -> room: xrf/bench/<name>/... ----------------------------------------------------


class Online(_Payload):
    """``xrf/bench/<name>/online`` (retained): true on every connect; false as the bench's last will
    or its clean goodbye. `conn` = (boot, connection number): a will of an older connection than
    the one the room knows live is ignored."""

    online: bool
    conn: tuple[Count, Count]


class AlarmSummary(_Payload):
    kind: Kind
    message: Text300 = ""
    t: Clock | None = None


class SelfcheckSummary(_Payload):
    verdict: Annotated[str, Field(max_length=32)] = ""
    t: Clock | None = None
    check: Count | None = None
    report: Text128 = ""
    message: Text300 = ""


class Status(_Payload):
    """``xrf/bench/<name>/status`` (retained, on every change at most 20 Hz and every second): what
    the bench's tile shows. `boot`, `seq`: its order (service.RoomState: a newer boot or seq
    replaces the shown one; an older one does not while the shown one is live)."""

    boot: Boot
    seq: Count
    t: Clock | None = None
    state: Text32 = "?"
    active: bool = False
    run_id: Count | None = None
    run_owner: Text64 = ""
    holder: Text64 = ""
    alarms: Annotated[list[AlarmSummary], Field(max_length=MAX_ALARMS)] = []
    selfcheck: SelfcheckSummary | None = None
    message: Text500 = ""
    assignments: Annotated[list[AssignmentId], Field(max_length=MAX_ASSIGNMENTS)] = []
    cycles: Count | None = None
    misses: Count | None = None
    cycle_rate: Annotated[float, Field(ge=0, le=1e7, allow_inf_nan=False)] | None = None
    cycle_freq: Annotated[float, Field(ge=0, le=1e7, allow_inf_nan=False)] | None = None
    accounts_version: Count = 0
    cpu_temp_c: Annotated[float, Field(ge=-100, le=300, allow_inf_nan=False)] | None = None
    throttled: Annotated[int, Field(ge=0, le=2**32)] | None = None
    disk_free_mb: Count | None = None
    events_queued: Count = 0
    events_dropped: Count = 0


class _Event(_Payload):
    boot: Boot
    seq: Count
    t: Clock


class RunStarted(_Event):
    kind: Literal["run_started"] = "run_started"
    run_id: Count
    owner: Text64
    build: Text128 = ""


class RunEnded(_Event):
    kind: Literal["run_ended"] = "run_ended"
    run_id: Count
    owner: Text64
    end_reason: Text32 = ""
    cycles: Count = 0
    misses: Count = 0


class AlarmEvent(_Event):
    kind: Literal["alarm"] = "alarm"
    alarm: Kind
    message: Text300 = ""
    run_id: Count | None = None


class SelfcheckEvent(_Event):
    kind: Literal["selfcheck"] = "selfcheck"
    verdict: Annotated[str, Field(max_length=32)] = ""
    check: Count | None = None
    report: Text128 = ""


class AssignmentEvent(_Event):
    kind: Literal["assignment"] = "assignment"
    id: AssignmentId
    name: Text64 = ""


EventModels = (RunStarted, RunEnded, AlarmEvent, SelfcheckEvent, AssignmentEvent)
Event = Annotated[RunStarted | RunEnded | AlarmEvent | SelfcheckEvent | AssignmentEvent, Field(discriminator="kind")]
"""``xrf/bench/<name>/event`` (QoS 1, queued while the broker is away): one of the kinds above;
the room drops a (boot, seq) it has seen."""


class Reply(_Payload):
    """``xrf/bench/<name>/reply`` (QoS 1): a bench's answer to a command (commands.py). The room
    keeps one answer per bench for an id it sent, nothing else."""

    id: CommandId
    cmd: Text32
    ok: bool = False
    error: Text300 = ""
    t_recv: Clock
    t_sent: Clock | None = None
    t_done: Clock | None = None
    # stop
    accepted: bool | None = None
    state: Text32 | None = None
    reason: Text300 | None = None
    t_loop: Clock | None = None
    note: Text300 | None = None
    # selfcheck
    skipped: Text32 | None = None
    check: Count | None = None
    # collect
    runs: Count | None = None
    bytes: Count | None = None
    left_out: Count | None = None
    # grades
    graded: Count | None = None


class GradeProgress(_Payload):
    parallel: Count = 0
    total: Count = 0
    queued: Count = 0
    running: Count = 0
    done: Count = 0


# a scenario's check id (grading/scenario.py: letters, digits, _ and -)
CheckId = Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_-]{0,63}$")]
Points = Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)]


class GradeCheck(_Payload):
    id: CheckId
    kind: Kind
    points: Points


class GradeCell(_Payload):
    earned: Points
    passed: bool
    value: Annotated[float, Field(ge=-1e300, le=1e300, allow_inf_nan=False)] | None = None


class GradeRow(_Payload):
    """One project's latest result on the bench that sent it (grading/service.py's table row)."""

    project: Count
    owner: Annotated[str, Field(pattern=USERNAME_RE.pattern)]
    name: Text128 = ""
    job: Literal["queued", "running", "done"] | None = None
    build: Text128 = ""
    status: Literal[GRADE_STATUSES + ("not graded",)]  # type: ignore[valid-type]
    reason: Text300 = ""
    earned: Points = 0.0
    points: Points = 0.0
    graded_at: Clock | None = None
    run: Count | None = None
    checks: Annotated[dict[CheckId, GradeCell], Field(max_length=SCENARIO_MAX_ITEMS)] = {}


class Grades(_Payload):
    """``xrf/bench/<name>/grades`` (QoS 1): the bench's grading table of one assignment, sent when
    the room asks (a ``grades`` command) and every second while its re-run goes on. The room
    keeps the newest (boot, seq) per (assignment, bench): the topic names the bench, so its rows
    can only ever be its own. `error`: why there is no table (no scenario, no such assignment)."""

    boot: Boot
    seq: Count
    t: Clock
    assignment: AssignmentId
    checks: Annotated[list[GradeCheck], Field(max_length=SCENARIO_MAX_ITEMS)] = []
    rows: Annotated[list[GradeRow], Field(max_length=MAX_GRADE_ROWS)] = []
    left_out: Count = 0  # rows that did not fit into GRADES_MAX_BYTES
    progress: GradeProgress = GradeProgress()
    error: Text300 = ""


# ---- room -> benches ------------------------------------------------------------------------


class _Command(_Payload):
    id: CommandId
    by: Text64 = ""
    t: Clock


class Stop(_Command):
    cmd: Literal["stop"] = "stop"


class Message(_Command):
    cmd: Literal["message"] = "message"
    text: Annotated[str, Field(min_length=1, max_length=500)]


class Selfcheck(_Command):
    cmd: Literal["selfcheck"] = "selfcheck"
    profile: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")] = Settings.sim


class Collect(_Command):
    cmd: Literal["collect"] = "collect"
    collection: Annotated[str, Field(pattern=r"^[0-9a-f]{8,32}$")]
    assignment: AssignmentId
    formats: Annotated[list[Literal["csv", "mat", "parquet"]], Field(max_length=3)] = []


class Grade(_Command):
    """The bench sends its grading table of `assignment` (``xrf/bench/<name>/grades``); with
    `scenario`, it keeps that scenario first (checked against the assignment's sources there: a
    refusal is the reply's error, with its line); with `rerun`, it grades every student's latest
    build (its own queue: bounded parallel) and sends the table every second until done."""

    cmd: Literal["grades"] = "grades"
    assignment: AssignmentId
    rerun: bool = False
    scenario: Annotated[str, Field(min_length=1, max_length=SCENARIO_MAX_BYTES)] | None = None


Command = Annotated[Stop | Message | Selfcheck | Collect | Grade, Field(discriminator="cmd")]
"""``xrf/cmd/<name>`` and ``xrf/cmd/all`` (QoS 1): only the room may publish there (the ACL)."""


class CommandHead(_Payload):
    """What a bench reads of a command it cannot parse, to answer that it could not."""

    id: CommandId
    cmd: Text32


class Account(_Payload):
    username: Annotated[str, Field(pattern=USERNAME_RE.pattern)]
    role: Role
    password_hash: Annotated[str, Field(pattern=r"^\$argon2", max_length=512)]
    full_name: Annotated[str, Field(max_length=200)] = ""
    email: Annotated[str, Field(max_length=200)] = ""
    disabled: bool = False
    must_change: bool = False


class ClassList(_Payload):
    """``xrf/accounts`` (retained): the room's whole accounts table (accounts_sync.py); `version`
    only grows."""

    version: Count
    users: Annotated[list[Account], Field(max_length=CLASS_LIST_MAX)]


_B64_MAX = (INLINE_MAX + 2) // 3 * 4


class Assignment(_Payload):
    """``xrf/assignment/<id>`` (retained): a published assignment (assignments.py); the archive
    inline when small, else fetched from `path` with a token the bench signs."""

    id: AssignmentId
    name: Text64
    by: Text64 = ""
    t: Clock
    template: Text64 = ""
    size: Annotated[int, Field(ge=0, le=ASSIGNMENT_LIMITS.max_upload)]
    sha256: Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
    files: Count = 0
    path: Annotated[str, Field(pattern=r"^/api/room/assignments/[a-z0-9-]{1,40}/archive$")]
    inline: Annotated[str, Field(max_length=_B64_MAX, pattern=r"^[A-Za-z0-9+/]*={0,2}$")] | None = None


# ---- room -> benches: xrf/room/online --------------------------------------------------------


class RoomOnline(_Payload):
    """``xrf/room/online`` (retained): true once the room has subscribed to the benches' topics;
    false as its last will or its clean goodbye. A bench sends its queued events only while it is
    true: QoS 1 only reaches subscribers, so events sent while the room is away (a broker restart
    forgets every subscription) would be acknowledged by the broker and lost. `conn` names the room's
    connection (a random token each connect): the room puts itself back when an older connection's
    will says false after it connected again."""

    online: bool
    conn: Annotated[str, Field(pattern=r"^[0-9a-f]{1,32}$")]


# Parsers (TypeAdapter: the unions have no class of their own)
ONLINE = TypeAdapter(Online)
STATUS = TypeAdapter(Status)
EVENT: TypeAdapter[Event] = TypeAdapter(Event)
REPLY = TypeAdapter(Reply)
COMMAND: TypeAdapter[Command] = TypeAdapter(Command)
COMMAND_HEAD = TypeAdapter(CommandHead)
CLASS_LIST = TypeAdapter(ClassList)
ASSIGNMENT = TypeAdapter(Assignment)
ROOM_ONLINE = TypeAdapter(RoomOnline)

GRADES = TypeAdapter(Grades)

BENCH_LEAVES: dict[str, TypeAdapter[Any]] = {
    "online": ONLINE,
    "status": STATUS,
    "event": EVENT,
    "reply": REPLY,
    "grades": GRADES,
}
# a leaf's size limit, when not BENCH_MAX_BYTES
LEAF_MAX_BYTES: dict[str, int] = {"grades": GRADES_MAX_BYTES}


def build_event(kind: str, **fields: Any) -> Any:
    """The event model of `kind` (make's rules: every field declared)."""
    for model in EventModels:
        if model.model_fields["kind"].default == kind:
            return model.make(kind=kind, **fields)
    raise TypeError(f"no event kind {kind!r} (payloads.py)")


def build_command(cmd: str, **fields: Any) -> Any:
    for model in (Stop, Message, Selfcheck, Collect, Grade):
        if model.model_fields["cmd"].default == cmd:
            return model.make(cmd=cmd, **fields)
    raise TypeError(f"no command {cmd!r} (payloads.py)")


def safe_text(text: Any, limit: int) -> str:
    """Text of our own that goes into a bounded field: cut, never refused."""
    return re.sub(r"[\x00-\x08\x0b-\x1f]", " ", str(text))[:limit]
