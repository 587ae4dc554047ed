"""A grading scenario: the TOML file an educator writes beside an assignment (issue 32).

TOML because an educator writes it by hand: comments, no indentation rules, and Python reads it
with the standard library (tomllib). docs/educators/grading.md documents every key with examples.

Every mistake is refused with its line: a TOML syntax error (tomllib's own line), an unknown key,
an unknown command, an impossible check (a window that ends before it starts, points below zero,
a bound that no value can meet), an unknown signal (``check_signals`` against the signals a
project can log). Line numbers come from a scan of the text (``_Lines``): tomllib keeps none.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

import tomllib

from ..channels.names import COMMAND_NUMBERS
from ..errors import Invalid
from . import expr

MAX_BYTES = 64 << 10  # a scenario is a page of text, not data
MAX_DURATION_S = 300.0  # what one student's run may cost the queue
MAX_ITEMS = 200  # commands, setpoint segments, checks: each
MAX_TABLE_POINTS = 10_000
# The loop's commands: channels.h's XRF_CMDS, through the binding (one definition).
COMMANDS = tuple(COMMAND_NUMBERS)
CHECK_KINDS = (
    "rise_time",
    "overshoot",
    "settling_time",
    "steady_state_error",
    "bound",
    "reach",
    "state",
    "no_deadline_misses",
    "no_alarms",
    "expression",
)
STEP_KINDS = ("rise_time", "overshoot", "settling_time", "steady_state_error")
SETPOINT_KINDS = ("step", "ramp", "table")
SIGNAL_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
STATES = ("INITIALISED", "RUN", "PAUSED", "STOPPED")


class ScenarioError(Invalid):
    """A scenario refused: `line` (1-based, 0 when unknown) and the message, both in the detail."""

    def __init__(self, message: str, line: int = 0, name: str = "scenario") -> None:
        where = f"{name}:{line}: " if line else f"{name}: "
        super().__init__(where + message, detail={"error": message, "line": line, "file": name})
        self.line = line
        self.reason = message


@dataclass(frozen=True)
class Command:
    at: float  # seconds of loop time (periods of the grid: cycles run + missed) from the first cycle
    cmd: str
    line: int = 0


@dataclass(frozen=True)
class Setpoint:
    """One segment of a Ros2Xeno field's setpoint over time. step: `value` from `at`; ramp: from
    `start` to `end` going `from_value` -> `to`; table: `points` [(t, v)] linearly interpolated."""

    signal: str
    kind: str
    at: float = 0.0
    value: float = 0.0
    end: float = 0.0
    from_value: float = 0.0
    to: float = 0.0
    points: tuple[tuple[float, float], ...] = ()
    line: int = 0

    @property
    def start(self) -> float:
        return self.points[0][0] if self.kind == "table" else self.at

    def value_at(self, t: float) -> float | None:
        """This segment's value at loop time t, None before it starts (the previous one holds)."""
        if t < self.start:
            return None
        if self.kind == "step":
            return self.value
        if self.kind == "ramp":
            if t >= self.end:
                return self.to
            return self.from_value + (self.to - self.from_value) * (t - self.at) / (self.end - self.at)
        pts = self.points
        for (t0, v0), (t1, v1) in zip(pts, pts[1:], strict=False):
            if t0 <= t < t1:
                return v0 + (v1 - v0) * (t - t0) / (t1 - t0) if t1 > t0 else v1
        return pts[-1][1]


@dataclass(frozen=True)
class Check:
    """One check: its kind's parameters in `params` (documented in grading.md), `points` and the
    `message` a student sees when it fails."""

    id: str
    kind: str
    points: float
    message: str
    signal: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    line: int = 0
    signal_line: int = 0  # the line naming what it reads (signal = / expr =)

    def window(self, duration: float) -> tuple[float, float]:
        """The span of loop time the check looks at (its plot's span too)."""
        p = self.params
        if "during" in p:
            return float(p["during"][0]), float(p["during"][1])
        if self.kind in STEP_KINDS:
            return float(p["at"]), float(p.get("until", duration))
        if self.kind in ("reach", "state"):
            return 0.0, float(p["by"])
        return 0.0, duration


@dataclass(frozen=True)
class Scenario:
    name: str
    robot: str  # a plant of the plant table (XRF_SIM)
    duration: float  # seconds of loop time
    faults: str = ""  # XRF_SIM_FAULTS (xrf/sim.h)
    log: str = ""  # the log file's stem (logs/stage -> "stage"); "" = the run's only log
    run_by: float = 0.0  # the loop must be in RUN by then (0: 2 s after the last start command)
    commands: tuple[Command, ...] = ()
    setpoints: tuple[Setpoint, ...] = ()
    checks: tuple[Check, ...] = ()
    source: str = ""  # the text, kept to store it beside the assignment

    @property
    def max_points(self) -> float:
        return sum(c.points for c in self.checks)

    def setpoint_signals(self) -> set[str]:
        return {s.signal for s in self.setpoints}

    def check_signals(self) -> dict[str, int]:
        """Every log column a check reads -> the line that names it first."""
        out: dict[str, int] = {}
        for c in self.checks:
            names = [c.signal] if c.signal else []
            if c.kind == "expression":
                names += sorted(expr.names(c.params["expr"]))
            for n in names:
                if n and n not in expr.RESERVED:
                    out.setdefault(n, c.signal_line or c.line)
        return out

    def setpoints_at(self, t: float) -> dict[str, float]:
        """Each setpoint signal's value at loop time t: the latest segment that has started."""
        out: dict[str, float] = {}
        for s in sorted(self.setpoints, key=lambda s: s.start):
            v = s.value_at(t)
            if v is not None:
                out[s.signal] = v
        return out


class _Lines:
    """Where keys stand in the text: (array, index, key) -> line; (array, index, "") the header."""

    HEADER = re.compile(r"^\s*\[\[\s*([A-Za-z_]+)\s*\]\]")
    TABLE = re.compile(r"^\s*\[\s*([A-Za-z_]+)\s*\]")
    KEY = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*=")

    def __init__(self, text: str) -> None:
        self.at: dict[tuple[str, int, str], int] = {}
        counts: dict[str, int] = {}
        table, index = "", 0
        for n, line in enumerate(text.splitlines(), 1):
            if m := self.HEADER.match(line):
                table = m.group(1)
                index = counts.get(table, 0)
                counts[table] = index + 1
                self.at.setdefault((table, index, ""), n)
            elif m := self.TABLE.match(line):
                table, index = m.group(1), 0
                self.at.setdefault((table, 0, ""), n)
            elif m := self.KEY.match(line):
                self.at.setdefault((table, index, m.group(1)), n)

    def of(self, table: str, index: int, key: str = "") -> int:
        return self.at.get((table, index, key)) or self.at.get((table, index, ""), 0)


class _Reader:
    def __init__(self, name: str, lines: _Lines) -> None:
        self.name = name
        self.lines = lines

    def fail(self, msg: str, table: str, index: int = 0, key: str = "") -> ScenarioError:
        return ScenarioError(msg, self.lines.of(table, index, key), self.name)

    def number(self, d: dict[str, Any], key: str, table: str, i: int, default: float | None = None) -> float:
        if key not in d:
            if default is None:
                raise self.fail(f"'{key}' is missing", table, i)
            return default
        v = d[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(f"'{key}' must be a number, not {v!r}", table, i, key)
        return float(v)

    def text(self, d: dict[str, Any], key: str, table: str, i: int, default: str | None = None) -> str:
        if key not in d:
            if default is None:
                raise self.fail(f"'{key}' is missing", table, i)
            return default
        v = d[key]
        if not isinstance(v, str) or len(v) > 500:
            raise self.fail(f"'{key}' must be a text of at most 500 characters", table, i, key)
        return v

    def signal(self, d: dict[str, Any], key: str, table: str, i: int) -> str:
        v = self.text(d, key, table, i)
        if not SIGNAL_RE.match(v):
            raise self.fail(f"'{key}' = {v!r} is not a signal name", table, i, key)
        return v

    def keys(self, d: dict[str, Any], allowed: set[str], table: str, i: int) -> None:
        for k in d:
            if k not in allowed:
                raise self.fail(f"unknown key '{k}' (known here: {', '.join(sorted(allowed))})", table, i, k)

    def span(self, d: dict[str, Any], key: str, table: str, i: int) -> tuple[float, float] | None:
        if key not in d:
            return None
        v = d[key]
        ok = (
            isinstance(v, list)
            and len(v) == 2
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        )
        if not ok:
            raise self.fail(f"'{key}' must be [t1, t2] in seconds", table, i, key)
        t1, t2 = float(v[0]), float(v[1])
        if not (0 <= t1 < t2):
            raise self.fail(f"'{key}' = [{t1:g}, {t2:g}]: an empty window (need 0 <= t1 < t2)", table, i, key)
        return t1, t2


_SCENARIO_KEYS = {"name", "robot", "duration", "faults", "log", "run_by"}
_COMMON = {"id", "kind", "points", "message", "signal"}
_CHECK_KEYS: dict[str, set[str]] = {
    "rise_time": {"at", "to", "from", "until", "max"},
    "overshoot": {"at", "to", "from", "until", "max_percent"},
    "settling_time": {"at", "to", "from", "until", "band_percent", "max"},
    "steady_state_error": {"at", "to", "from", "until", "window", "max"},
    "bound": {"during", "max_abs", "min", "max"},
    "reach": {"value", "tolerance", "by"},
    "state": {"state", "by"},
    "no_deadline_misses": set(),
    "no_alarms": set(),
    "expression": {"expr", "during", "require"},
}


def load(text: str, name: str = "scenario.toml", robots: tuple[str, ...] | None = None) -> Scenario:
    """Parse and check a scenario; ScenarioError (an Invalid, 422) with the line on any mistake.
    `robots`: the plant names allowed (the plant table; None: not checked here)."""
    if len(text.encode()) > MAX_BYTES:
        raise ScenarioError(f"larger than {MAX_BYTES >> 10} KiB", 0, name)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        msg = str(exc)
        m = re.search(r"at line (\d+)", msg)
        line = int(m.group(1)) if m else len(text.splitlines())
        raise ScenarioError(f"not valid TOML: {re.sub(r' ?[(]at .*[)]$', '', msg)}", line, name) from None
    lines = _Lines(text)
    r = _Reader(name, lines)
    for k in doc:
        if k not in ("scenario", "commands", "setpoints", "checks"):
            raise ScenarioError(f"unknown section '{k}' (scenario, commands, setpoints, checks)", lines.of(k, 0), name)
    head = doc.get("scenario")
    if not isinstance(head, dict):
        raise ScenarioError("a [scenario] section with robot and duration is needed", 1, name)
    r.keys(head, _SCENARIO_KEYS, "scenario", 0)
    robot = r.text(head, "robot", "scenario", 0)
    if robots is not None and robot not in robots:
        raise r.fail(f"unknown robot {robot!r}; have: {', '.join(robots)}", "scenario", 0, "robot")
    duration = r.number(head, "duration", "scenario", 0)
    if not 0 < duration <= MAX_DURATION_S:
        raise r.fail(
            f"duration {duration:g} s: must be above 0 and at most {MAX_DURATION_S:g} s", "scenario", 0, "duration"
        )
    run_by = r.number(head, "run_by", "scenario", 0, 0.0)
    if run_by < 0 or run_by > duration:
        raise r.fail("run_by must lie within the duration", "scenario", 0, "run_by")
    log = r.text(head, "log", "scenario", 0, "")
    if log and not SIGNAL_RE.match(log):
        raise r.fail(f"log {log!r}: a file stem such as 'stage'", "scenario", 0, "log")
    faults = r.text(head, "faults", "scenario", 0, "")
    if not re.fullmatch(r"[A-Za-z0-9_.,:=+-]*", faults):
        raise r.fail(f"faults {faults!r}: letters, digits and , : = . + - only (xrf/sim.h)", "scenario", 0, "faults")

    commands = [_command(r, d, i, duration) for i, d in enumerate(_array(r, doc, "commands"))]
    if not any(c.cmd == "start" for c in commands):
        raise ScenarioError("no 'start' command: the controller would never run", lines.of("commands", 0), name)
    setpoints = [_setpoint(r, d, i, duration) for i, d in enumerate(_array(r, doc, "setpoints"))]
    checks = [_check(r, d, i, duration) for i, d in enumerate(_array(r, doc, "checks"))]
    if not checks:
        raise ScenarioError("no [[checks]]: nothing to grade", len(text.splitlines()), name)
    ids = set()
    for i, c in enumerate(checks):
        if c.id in ids:
            raise r.fail(f"two checks have the id {c.id!r}", "checks", i, "id")
        ids.add(c.id)
    return Scenario(
        name=r.text(head, "name", "scenario", 0, name),
        robot=robot,
        duration=duration,
        faults=faults,
        log=log,
        run_by=run_by,
        commands=tuple(sorted(commands, key=lambda c: c.at)),
        setpoints=tuple(setpoints),
        checks=tuple(checks),
        source=text,
    )


def check_signals(scenario: Scenario, setpoint_fields: set[str], log_columns: set[str], name: str = "") -> None:
    """Refuse a signal the project cannot have: a setpoint not in its Ros2Xeno message, a checked
    signal not among what it logs (`log_columns`), each with the line naming it."""
    name = name or "scenario.toml"
    for s in scenario.setpoints:
        if s.signal not in setpoint_fields:
            have = ", ".join(sorted(setpoint_fields)) or "none"
            raise ScenarioError(f"unknown setpoint signal {s.signal!r} (Ros2Xeno has: {have})", s.line, name)
    for sig, line in scenario.check_signals().items():
        if sig not in log_columns:
            have = ", ".join(sorted(log_columns)) or "none"
            raise ScenarioError(f"unknown signal {sig!r} (the log has: {have})", line, name)


def _array(r: _Reader, doc: dict[str, Any], key: str) -> list[dict[str, Any]]:
    v = doc.get(key, [])
    if not isinstance(v, list) or not all(isinstance(d, dict) for d in v):
        raise r.fail(f"'{key}' must be [[{key}]] tables", key, 0)
    if len(v) > MAX_ITEMS:
        raise r.fail(f"more than {MAX_ITEMS} [[{key}]]", key, MAX_ITEMS)
    return v


def _time(
    r: _Reader, d: dict[str, Any], key: str, table: str, i: int, duration: float, default: float | None = None
) -> float:
    t = r.number(d, key, table, i, default)
    if not 0 <= t <= duration:
        raise r.fail(f"'{key}' = {t:g} s lies outside the scenario (0 .. {duration:g} s)", table, i, key)
    return t


def _command(r: _Reader, d: dict[str, Any], i: int, duration: float) -> Command:
    r.keys(d, {"at", "cmd"}, "commands", i)
    cmd = r.text(d, "cmd", "commands", i)
    if cmd not in COMMANDS:
        raise r.fail(f"unknown command {cmd!r}; have: {', '.join(COMMANDS)}", "commands", i, "cmd")
    return Command(_time(r, d, "at", "commands", i, duration), cmd, r.lines.of("commands", i))


def _setpoint(r: _Reader, d: dict[str, Any], i: int, duration: float) -> Setpoint:
    t = "setpoints"
    kind = r.text(d, "kind", t, i)
    if kind not in SETPOINT_KINDS:
        raise r.fail(f"unknown setpoint kind {kind!r}; have: {', '.join(SETPOINT_KINDS)}", t, i, "kind")
    line = r.lines.of(t, i)
    sig = r.signal(d, "signal", t, i)
    if kind == "step":
        r.keys(d, {"kind", "signal", "at", "value"}, t, i)
        return Setpoint(sig, kind, at=_time(r, d, "at", t, i, duration), value=r.number(d, "value", t, i), line=line)
    if kind == "ramp":
        r.keys(d, {"kind", "signal", "at", "end", "from", "to"}, t, i)
        at, end = _time(r, d, "at", t, i, duration), _time(r, d, "end", t, i, duration)
        if end <= at:
            raise r.fail(f"a ramp that ends ({end:g} s) before it starts ({at:g} s)", t, i, "end")
        return Setpoint(
            sig, kind, at=at, end=end, from_value=r.number(d, "from", t, i), to=r.number(d, "to", t, i), line=line
        )
    r.keys(d, {"kind", "signal", "points"}, t, i)
    pts = d.get("points") or []
    ok = isinstance(pts, list) and 0 < len(pts) <= MAX_TABLE_POINTS
    ok = ok and all(
        isinstance(p, list) and len(p) == 2 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in p)
        for p in pts
    )
    if not ok:
        raise r.fail(f"'points' must be [[t, value], ...] (1 to {MAX_TABLE_POINTS} pairs)", t, i, "points")
    table = tuple((float(a), float(b)) for a, b in pts)
    if (
        any(b[0] < a[0] for a, b in zip(table, table[1:], strict=False))
        or not 0 <= table[0][0] <= table[-1][0] <= duration
    ):
        raise r.fail("'points' times must rise and lie within the duration", t, i, "points")
    return Setpoint(sig, kind, points=table, line=line)


def _check(r: _Reader, d: dict[str, Any], i: int, duration: float) -> Check:
    t = "checks"
    kind = r.text(d, "kind", t, i)
    if kind not in CHECK_KINDS:
        raise r.fail(f"unknown check kind {kind!r}; have: {', '.join(CHECK_KINDS)}", t, i, "kind")
    r.keys(d, _COMMON | _CHECK_KEYS[kind], t, i)
    points = r.number(d, "points", t, i, 1.0)
    if not 0 <= points <= 1000:
        raise r.fail("points must be 0 .. 1000", t, i, "points")
    cid = r.text(d, "id", t, i, f"{kind}-{i + 1}")
    if not SIGNAL_RE.match(cid.replace("-", "_")):
        raise r.fail(f"id {cid!r}: letters, digits, _ and -", t, i, "id")
    message = r.text(d, "message", t, i, "")
    needs_signal = kind not in ("state", "no_deadline_misses", "no_alarms", "expression")
    signal = r.signal(d, "signal", t, i) if needs_signal else ""
    if "signal" in d and not needs_signal:
        raise r.fail(f"a {kind} check reads no signal", t, i, "signal")
    p: dict[str, Any] = {}
    during = r.span(d, "during", t, i)
    if during is not None:
        if during[1] > duration:
            raise r.fail(f"'during' ends after the scenario ({duration:g} s)", t, i, "during")
        p["during"] = during

    def positive(key: str, default: float | None = None) -> float:
        v = r.number(d, key, t, i, default)
        if v <= 0:
            raise r.fail(f"'{key}' = {v:g}: no value can meet it (must be above 0)", t, i, key)
        return v

    if kind in STEP_KINDS:
        p["at"] = _time(r, d, "at", t, i, duration)
        p["to"] = r.number(d, "to", t, i)
        if "from" in d:
            p["from"] = r.number(d, "from", t, i)
        p["until"] = _time(r, d, "until", t, i, duration, duration)
        if p["until"] <= p["at"]:
            raise r.fail(f"'until' ({p['until']:g} s) is not after the step ({p['at']:g} s)", t, i, "until")
        if kind == "overshoot":
            p["max_percent"] = r.number(d, "max_percent", t, i)
            if p["max_percent"] < 0:
                raise r.fail("'max_percent' below 0: no response can meet it", t, i, "max_percent")
        elif kind == "settling_time":
            p["band_percent"] = positive("band_percent", 2.0)
            p["max"] = positive("max")
        elif kind == "steady_state_error":
            p["window"] = positive("window", 0.1)
            p["max"] = positive("max")
            if p["window"] > p["until"] - p["at"]:
                raise r.fail("'window' is longer than the span from the step to 'until'", t, i, "window")
        else:
            p["max"] = positive("max")
        if kind in ("rise_time", "settling_time") and p["max"] > p["until"] - p["at"]:
            raise r.fail(f"'max' ({p['max']:g} s) is longer than the span the check sees", t, i, "max")
    elif kind == "bound":
        if "during" not in p:
            p["during"] = (0.0, duration)
        for k in ("max_abs", "min", "max"):
            if k in d:
                p[k] = r.number(d, k, t, i)
        if not any(k in p for k in ("max_abs", "min", "max")):
            raise r.fail("a bound needs max_abs, min or max", t, i)
        if p.get("max_abs", 1.0) < 0:
            raise r.fail("'max_abs' below 0: no value can meet it", t, i, "max_abs")
        if "min" in p and "max" in p and p["min"] > p["max"]:
            raise r.fail(f"min {p['min']:g} above max {p['max']:g}: no value can meet it", t, i, "min")
    elif kind == "reach":
        p["value"] = r.number(d, "value", t, i)
        p["tolerance"] = positive("tolerance")
        p["by"] = _time(r, d, "by", t, i, duration)
    elif kind == "state":
        p["state"] = r.text(d, "state", t, i, "RUN")
        if p["state"] not in STATES:
            raise r.fail(f"state {p['state']!r}; one of {', '.join(STATES)}", t, i, "state")
        p["by"] = _time(r, d, "by", t, i, duration)
    elif kind == "expression":
        source = r.text(d, "expr", t, i)
        try:
            expr.compile_expr(source)
        except expr.ExprError as exc:
            raise r.fail(f"expr: {exc}", t, i, "expr") from None
        p["expr"] = source
        p["require"] = r.text(d, "require", t, i, "always")
        if p["require"] not in ("always", "sometime", "final"):
            raise r.fail("require: always, sometime or final", t, i, "require")
        if "during" not in p:
            p["during"] = (0.0, duration)
    return Check(
        cid,
        kind,
        points,
        message,
        signal,
        p,
        r.lines.of(t, i),
        r.lines.of(t, i, "expr" if kind == "expression" else "signal"),
    )
