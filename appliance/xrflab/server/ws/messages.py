"""The WebSocket protocol of /ws: one pydantic model per message kind, both directions.

This module is the protocol's one definition. The appliance publishes it as JSON Schema at
``GET /api/ws-schema`` (next to ``/openapi.json``); the dashboard dispatches on the kinds it
lists (frontend/app.js); the /ws handler parses every incoming message with these models; and
tests/server/test_ws_schema.py checks that every message a realistic session sends matches.

Every message is a JSON object whose ``type`` names its kind. Server -> browser kinds are topics
(a client may ``subscribe`` to some of them: ``TOPICS``) except ``ack``, ``pong`` and
``error``, which go to the asking client only. Adding a kind: a model here (with its ``type``
Literal), listed in ``SERVER`` or ``CLIENT``; a client kind also gets its permission in
``api.WS_PERMS``. docs/developers/architecture.md ("WebSocket messages") has the walk-through.

Senders build the model (``StateMessage(run_id=..., ...)``; an outgoing model's ``type`` has its
kind as default, and stays required in the published schema) and hand it to the hub, which takes
nothing else (``ServerMessage``, ``ReplyMessage``). The model is validated when it is built, so a
sender whose message does not fit fails there, with the field named, and never reaches a browser.
The streams are the exception: telemetry (5 messages a second of six samples each), the
monitor ring's lines and the timing message (once a second, nine models) are sent as their wire
fields, built by their producer, the first of a run checked against ``TelemetryMessage``,
``MonitorMessage``, ``TimingMessage`` (``Hub.publish_fields``: the model cost more than the fan-out).
On the wire a message has the fields its sender set, nothing else: a field left out is absent (not
null), as app.js and the room's bench publisher read them (``hub.unpack``: exclude_unset).

Outgoing models forbid fields they do not declare, so a sender that grows a field without
saying so here fails at once instead of drifting silently. Incoming models accept extra
fields (a client may tag a request with its own data; ``id`` is echoed back).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Literal, Union, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    TypeAdapter,
    ValidationError,
    model_validator,
)


def _type_required(schema: dict[str, Any]) -> None:
    """An outgoing model's `type` has a default (its kind: senders need not spell it) but every
    message carries it: the published schema says it is required, as it did before the default."""
    kind = schema.get("properties", {}).get("type")
    if kind is None:
        return
    kind.pop("default", None)
    if "type" not in schema.setdefault("required", []):
        schema["required"].insert(0, "type")


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra=_type_required)


class _In(BaseModel):
    model_config = ConfigDict(extra="allow")

    # The permission (server/security/auth.py's Perm, by value) a client needs to send this kind:
    # server/http/runs.py's WS_PERMS is made from it, so a new kind cannot lack one.
    perm: ClassVar[str]

    id: Any = Field(default=None, description="any value; echoed in the reply so a client can match it")


# ---- server -> browser --------------------------------------------------------------------------


class Rejected(_Out):
    ticket: int
    cmd: int
    name: str = Field(description="command name")
    reason: str


class StateMessage(_Out):
    """The loop's state, whenever the state, a rejection or liveness changes."""

    type: Literal["state"] = "state"
    run_id: int | None
    active: bool = Field(description="the loop cycles; false: no run, or the run ended")
    state: int = Field(description="state number (GET /api/state-machine), 0 without a run")
    name: str = Field(description="state name, 'NO RUN' without a run")
    allowed: list[str] = Field(description="commands the loop accepts now (rt_core's command table)")
    rejected: Rejected | None = Field(description="the last command the loop rejected")
    last_error: int = Field(description="the last negative hook return")
    cycles: int | None = Field(default=None, description="cycles so far (absent without a run)")


class MsgField(_Out):
    name: str
    type: str = Field(description=".msg type, e.g. float64")
    count: int | None = Field(description="array length, null for a scalar")


class Confinement(_Out):
    mode: str
    layers: dict[str, str] = Field(description="layer -> '' (holds) or why not")
    missing: dict[str, str]
    notes: list[str]
    confined: bool


class RunMessage(_Out):
    """A run started or ended, or the current one (a new client's first message)."""

    type: Literal["run"] = "run"
    event: Literal["current", "started", "ended"]
    run: dict[str, Any] | None = Field(
        description="the run record (RunRecord in /openapi.json); null before the first run"
    )
    active: bool
    redacted: bool | None = Field(default=None, description="true: someone else's run, owner's fields blank")
    program: str | None = None
    cycle_freq: int | None = None
    backend: str | None = None
    transport: str | None = None
    channels: int | None = Field(
        default=None,
        description="the bench's channel count (the run's shared-memory header, 1..XRF_MAX_CHANNELS): "
        "telemetry's enc, pwm, dout have this many values, din twice as many",
    )
    ros2xeno: list[MsgField] | None = Field(default=None, description="setpoint fields (Ros2Xeno)")
    xeno2ros: list[MsgField] | None = Field(default=None, description="output fields (Xeno2Ros)")
    setpoint: dict[str, Any] | None = Field(default=None, description="the Ros2Xeno values applied now")
    confinement: Confinement | None = None


class TelemetrySample(_Out):
    """One sample of the decimated stream (telemetry_hz): the loop's state, channels and outputs
    at one cycle."""

    cycle: int
    t_ns: int
    t: float = Field(description="seconds since the loop's first deadline")
    state: int
    enc: list[int]
    din: list[int]
    pwm: list[int]
    dout: list[int]
    xeno2ros: dict[str, Any] = Field(description="the controller's outputs ({} for someone else's run)")
    ros2xeno_t_sent_ns: int = Field(description="when the Ros2Xeno the loop had at this cycle was sent")


class TelemetryMessage(_Out):
    """Samples of the decimated stream (telemetry_hz samples a second), telemetry_per_message of
    them a message, oldest first (fewer messages: each costs the appliance a wake-up and a socket
    write, issue 30 item 4); the only topic a slow client loses (oldest first)."""

    type: Literal["telemetry"] = "telemetry"
    run_id: int
    samples: list[TelemetrySample] = Field(description="oldest first; the page plays them out at their own spacing")
    ros2xeno: dict[str, Any] = Field(
        default_factory=dict,
        description=(
            "the Ros2Xeno the loop has now (at the newest sample), whoever wrote it ({} for someone else's run); "
            "a sample whose ros2xeno_t_sent_ns differs from the newest's had an earlier one"
        ),
    )
    lost: int = Field(description="samples this reader lost to the ring so far")


class StageSummary(_Out):
    count: int
    min: int
    max: int
    mean: float
    p50: int
    p99: int


class Histogram(_Out):
    edges: list[int] = Field(description="lower edge (ns) of each non-empty bucket")
    counts: list[int]


class TimingMessage(_Out):
    """Once per timing period (1 s): cycles, misses, per-stage summaries and histograms."""

    type: Literal["timing"] = "timing"
    run_id: int
    cycles: int
    misses: int
    cycle_freq: int
    stages: dict[str, StageSummary]
    jitter: Histogram = Field(description="the wake-up stage's histogram")
    histograms: dict[str, Histogram]
    telemetry_sent: int
    log_lost: int
    host_lost: int


class MonitorLine(_Out):
    text: str
    cycle: int | None = None
    t_ns: int | None = None


class MonitorMessage(_Out):
    """Console lines: the loop's monitor ring, its stdout/stderr, the appliance's notes."""

    type: Literal["monitor"] = "monitor"
    run_id: int
    source: Literal["monitor", "stdout", "appliance"]
    lines: list[MonitorLine]
    lost: int | None = Field(default=None, description="monitor lines lost so far (source monitor)")


class AlarmMessage(_Out):
    """Something someone must see: the dashboard's alarm bar (or its confinement banner)."""

    type: Literal["alarm"] = "alarm"
    kind: Literal[
        "crash",
        "hang",
        "deadline_miss",
        "confinement",
        "disk",
        "log",
        "room",
        "corrupt_channel",
        "memory",
        "pids",
        "cpu",
        "host_lost",
    ]
    message: str
    run_id: int | None = None
    end_reason: str | None = Field(default=None, description="crash, hang: runs.END_REASONS")
    exit_code: int | None = None
    exit_signal: int | None = None
    safe_state: str | None = Field(default=None, description="crash, hang: how the outputs were made safe")
    event_ns: int | None = Field(default=None, description="crash, hang: CLOCK_MONOTONIC when the watcher saw it")
    safe_ns: int | None = Field(default=None, description="crash, hang: when the outputs were safe")
    heartbeat_ns: int | None = Field(default=None, description="crash, hang: the loop's last cycle start")
    watcher_rt: bool | None = None
    missing: dict[str, str] | None = Field(default=None, description="confinement: layer -> why it does not hold")
    started: bool | None = Field(
        default=None,
        description="confinement: true when the run started without the layers in `missing` (the "
        "dashboard's banner), false when it was refused (not started)",
    )
    misses: int | None = Field(default=None, description="deadline_miss: misses in total")
    new: int | None = Field(default=None, description="deadline_miss: misses since the last alarm")
    from_: str | None = Field(default=None, alias="from", description="room: who sent it")


class BuildMessage(_Out):
    """A build's progress: a bundled example's (`build`) or an uploaded project's (`build_id`)."""

    type: Literal["build"] = "build"
    build: str | None = Field(default=None, description="a bundled build's name")
    build_id: int | None = Field(default=None, description="a project build's id")
    project_id: int | None = None
    owner: str | None = None
    status: str | None = Field(default=None, description="building | ready | failed; projects: queued | ok | ...")
    result: str | None = None
    line: str | None = Field(default=None, description="one line of compiler output")
    error: str | None = None
    position: int | None = Field(default=None, description="queued: place in the build queue")
    duration: float | None = None


class Who(_Out):
    id: int
    username: str
    role: str


class LeaseHolder(Who):
    since: float = Field(description="Unix time")


class LeaseMessage(_Out):
    """Who holds the bench and who queues for it (server/security/lease.py)."""

    type: Literal["lease"] = "lease"
    event: str = Field(
        description="current | take | takeover | released | handover | queue | unqueue | intervention "
        "(server/security/lease.py)"
    )
    holder: LeaseHolder | None
    queue: list[Who]
    idle_s: float
    idle_left_s: float | None
    by: Who | None = Field(default=None, description="who made the change (null: the appliance)")
    previous: Who | None = None
    reason: str | None = None
    command: str | None = Field(
        default=None, description="event intervention: the command (pause | stop) `by` sent to the holder's run"
    )


class SelfcheckMessage(BaseModel):
    """A bench self-check's event (server/http/selfcheck.py): `begin` from the appliance, the
    checker's own events (xrflab/selfcheck.py, their fields are the checker's), `report` or
    `error` last."""

    model_config = ConfigDict(extra="allow", json_schema_extra=_type_required)

    type: Literal["selfcheck"] = "selfcheck"
    check: int
    event: str = Field(description="begin | start | progress | step | end | error | report")


class RosMessage(_Out):
    """The ROS 2 bridge of the current run (server/runs/ros_bridge.py)."""

    type: Literal["ros"] = "ros"
    enabled: bool
    state: Literal["running", "stopped", "failed"]
    pid: int | None
    run_id: int | None
    user: str
    topics: list[str]
    last_error: str
    restarts: int
    started: float | None
    scheduling: str
    output: str
    configured_user: str


class ParamChange(_Out):
    name: str
    old: float
    new: float


class ParamsMessage(_Out):
    """The current run's tunable parameters (xrflab/params/service.py): the whole table when a
    run starts or a set lands (``event`` "table" / "applied"), with the changes of an applied set
    and the cycle the loop applied them at. The bench's: every watcher sees it."""

    type: Literal["params"] = "params"
    event: Literal["table", "applied"]
    run_id: int | None
    params: list[dict[str, Any]] = Field(description="name, unit, default, min, max, has_range, value, source")
    origin: str = Field(description="none | 20sim: what the table was made from")
    note: str = ""
    cycle: int | None = None
    who: str = ""
    changes: list[ParamChange] = Field(default_factory=list)


class AckMessage(_Out):
    """To the asking client: a command's outcome, the setpoint applied, the topics subscribed."""

    type: Literal["ack"] = "ack"
    id: Any = None
    cmd: str | int | None = None
    ticket: int | None = None
    accepted: bool | None = None
    state: int | None = None
    name: str | None = Field(default=None, description="command: the state after it")
    reason: str | None = None
    setpoint: dict[str, Any] | None = Field(default=None, description="setpoint: every Ros2Xeno value now applied")
    topics: list[str] | None = Field(default=None, description="subscribe: the topics now subscribed")


class PongMessage(_Out):
    type: Literal["pong"] = "pong"
    id: Any = None
    t: Any = Field(default=None, description="the ping's t, echoed")


class ErrorMessage(_Out):
    """To the asking client: why its message was refused; the connection carries on."""

    type: Literal["error"] = "error"
    error: str
    id: Any = None
    request: str | None = Field(default=None, description="the refused message's type")
    denied: bool | None = Field(default=None, description="refused for want of a permission")


# What the hub takes (hub.publish, publish_to_owner, publish_to_educators, a snapshot source's
# messages): a model of these, never a dict (the hub checks it at run time too). The one list of
# server kinds: SERVER, SERVER_KINDS, TOPICS and the published schema are made from it.
ServerMessage = (
    StateMessage
    | RunMessage
    | TelemetryMessage
    | TimingMessage
    | MonitorMessage
    | AlarmMessage
    | BuildMessage
    | LeaseMessage
    | SelfcheckMessage
    | RosMessage
    | ParamsMessage
    | AckMessage
    | PongMessage
    | ErrorMessage
)
# What goes to the asking client only (hub.Client.reply): every other server kind is a topic.
ReplyMessage = AckMessage | PongMessage | ErrorMessage
SERVER: tuple[type[BaseModel], ...] = get_args(ServerMessage)


def kind_of(model: type[BaseModel]) -> str:
    """The `type` value a model's messages carry."""
    return model.model_fields["type"].annotation.__args__[0]  # type: ignore[union-attr]


# Topics a client may subscribe to (the hub's per-client filter): the server kinds but the replies.
TOPICS = frozenset(kind_of(m) for m in SERVER if m not in get_args(ReplyMessage))


# ---- browser -> server --------------------------------------------------------------------------
# The checks run before the typed fields so that a refusal reads as it always has (tests/server/
# test_ws.py BAD_INPUT): pydantic's own wording is kept for what they do not cover.


def _value_ok(name: str, value: Any) -> None:
    for v in value if isinstance(value, list) else [value]:
        if isinstance(v, bool):
            continue
        if not isinstance(v, (int, float)):
            raise ValueError(f"field {name}: {value!r} is not a number")
        if not math.isfinite(v):
            raise ValueError(f"field {name}: {v!r} is not a finite number")


class CommandRequest(_In):
    """A state machine command (needs STOP for stop/pause, DRIVE for the rest); answered by `ack`."""

    perm = "stop"  # enough for a safe command; runs.py asks DRIVE for any other
    type: Literal["command"]
    cmd: StrictStr | StrictInt = Field(description="a command name (GET /api/state-machine) or number")

    @model_validator(mode="before")
    @classmethod
    def _check(cls, data: Any) -> Any:
        cmd = data.get("cmd") if isinstance(data, dict) else None
        if isinstance(cmd, bool) or not isinstance(cmd, (str, int)):
            raise ValueError("command needs 'cmd': a command name or number")
        return data


Scalar = StrictBool | StrictInt | StrictFloat


class SetpointRequest(_In):
    """New Ros2Xeno values (DRIVE); fields not named keep their value. Answered by `ack`."""

    perm = "drive"
    type: Literal["setpoint"]
    fields: dict[str, Scalar | list[Scalar]] = Field(
        min_length=1, description="Ros2Xeno field -> number, bool or list (an array field)"
    )

    @model_validator(mode="before")
    @classmethod
    def _check(cls, data: Any) -> Any:
        fields = data.get("fields") if isinstance(data, dict) else None
        if not isinstance(fields, dict) or not fields:
            raise ValueError("setpoint needs 'fields': an object of field name -> value")
        for name, value in fields.items():
            _value_ok(name, value)
        return data


class SubscribeRequest(_In):
    """The topics this client wants from now on (all of them at first). Answered by `ack`."""

    perm = "watch"
    type: Literal["subscribe"]
    topics: list[Literal[tuple(sorted(TOPICS))]]  # type: ignore[valid-type]

    @model_validator(mode="before")
    @classmethod
    def _check(cls, data: Any) -> Any:
        topics = data.get("topics") if isinstance(data, dict) else None
        if not isinstance(topics, list) or not all(isinstance(t, str) for t in topics):
            raise ValueError("subscribe needs 'topics': a list of topic names")
        unknown = sorted(set(topics) - TOPICS)
        if unknown:
            raise ValueError(f"unknown topic(s) {', '.join(unknown)}; topics: {', '.join(sorted(TOPICS))}")
        return data


class PingRequest(_In):
    """Answered by `pong` with the same `t`."""

    perm = "watch"
    type: Literal["ping"]
    t: Any = None


# The one list of client kinds: CLIENT, CLIENT_KINDS, runs.py's WS_PERMS and the schema come from it.
ClientMessage = CommandRequest | SetpointRequest | SubscribeRequest | PingRequest
CLIENT: tuple[type[_In], ...] = get_args(ClientMessage)


SERVER_KINDS: dict[str, type[BaseModel]] = {kind_of(m): m for m in SERVER}
CLIENT_KINDS: dict[str, type[_In]] = {kind_of(m): m for m in CLIENT}

IncomingMessage = Annotated[ClientMessage, Field(discriminator="type")]


class BadMessage(ValueError):
    """An incoming message that does not fit its kind's model; str() is the reason for the client."""


def parse_incoming(kind: str, msg: dict[str, Any]) -> BaseModel:
    """The typed form of a client message of a known `kind` (api.WS_PERMS has looked it up)."""
    model = CLIENT_KINDS.get(kind)
    if model is None:
        raise BadMessage(f"unknown message type {kind!r}; types: {', '.join(CLIENT_KINDS)}")
    try:
        return model.model_validate(msg)
    except ValidationError as exc:
        err = exc.errors()[0]
        cause = (err.get("ctx") or {}).get("error")
        if isinstance(cause, ValueError):  # one of our checks: its sentence as it is
            raise BadMessage(str(cause)) from None
        where = ".".join(str(p) for p in err.get("loc", ()))
        raise BadMessage(f"{kind}: {where}: {err.get('msg')}" if where else f"{kind}: {err.get('msg')}") from None


# ---- the published schema -----------------------------------------------------------------------


def _union(models: tuple[type[BaseModel], ...]) -> Any:
    # Union[...] of a tuple built at run time: `X | Y` cannot spell it (ruff's UP007 rewrite to
    # `Annotated[models, ...]` made GET /api/ws-schema raise TypeError).
    return Annotated[Union[models], Field(discriminator="type")]  # noqa: UP007


def ws_schema() -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of /ws: `server` (what browsers receive) and `client` (what
    they may send), each a `oneOf` keyed by `type`; `kinds` lists every kind of each direction."""
    server = TypeAdapter(_union(SERVER)).json_schema(ref_template="#/$defs/{model}")
    client = TypeAdapter(_union(CLIENT)).json_schema(ref_template="#/$defs/{model}")
    defs = {**server.pop("$defs", {}), **client.pop("$defs", {})}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "XRF Lab WebSocket /ws",
        "description": (__doc__ or "").split("\n\n")[0],
        "kinds": {"server": list(SERVER_KINDS), "client": list(CLIENT_KINDS)},
        "topics": sorted(TOPICS),
        "server": server,
        "client": client,
        "$defs": defs,
    }
