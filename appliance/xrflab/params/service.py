"""The current run's tunable parameters: its table, atomic sets with the loop's confirmation, and
every applied change logged (the run's change table) and published to every watcher.

A set is checked whole before anything is written to the loop (unknown name, a value that is not
a finite number, out of range, no running loop): one refusal, nothing applied. Only then is it
written as one pending set, which the loop takes at one cycle boundary and confirms with that
cycle's number (rt_core's xrf/params.h). Who may set (the bench holder) is the route's rule.

The change log is the appliance's own file (``<data>/params/run-<id>.jsonl``, one JSON object per
changed parameter: run, cycle, t, name, old, new, who), never in the run folder the guest writes.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import stat
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from starlette.requests import HTTPConnection

from ..channels import ChannelsCorrupt
from ..channels import params as chparams
from ..errors import Conflict, Invalid, NotFound, Unavailable, XrfError
from ..server.runs.lifecycle import RunObserver
from ..server.ws.messages import ParamChange, ParamsMessage

if TYPE_CHECKING:
    from ..server.runs.run import Run
    from ..server.runs.store import RunRow
    from ..server.runs.supervisor import Supervisor
    from ..server.settings import Settings
    from ..server.ws.hub import Hub

log = logging.getLogger("xrflab.params")

# How long a set waits for the loop's confirmation: a loop takes it at its next cycle (1 ms at
# 1 kHz); a loop that does not in this time is not cycling (stopped in a debugger, starved).
ANSWER_TIMEOUT_S = 1.0
# A parameter without a declared range gets one around its default (a user may widen it).
PROPOSED_SPAN = 10.0
CHANGES_MAX = 100_000
# "Save as the project's parameters" (docs/students/tuning.md): a small file beside the project,
# saved as a new version through the editor's API; a run of the project starts with its values.
SAVED_FILE = "xrf_params.json"
SAVED_MAX_BYTES = 64 * 1024
SAVED_BY = "saved parameters"  # changes one run keeps in its log (a script setting at 1 kHz stops there)

NO_PARAMS_NOTE = {
    "none": "this controller declares no tunable parameters (xrf/tunable.hpp; docs/students/tuning.md)",
    "20sim": "the 20-sim export names no parameters (its tokens file has none: 20-sim inlined them as constants)",
}


def proposed_range(default: float) -> tuple[float, float]:
    span = max(abs(default) * PROPOSED_SPAN, 1.0)
    return (default - span, default + span)


@dataclass
class RunParams:
    run_id: int
    owner: str
    table: chparams.ParamTable
    values: list[float]
    ranges: list[tuple[float, float]]
    by_name: dict[str, int]
    changes: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def describe(self) -> list[dict[str, Any]]:
        return [
            {
                "name": p.name,
                "unit": p.unit,
                "default": p.default,
                "min": self.ranges[p.index][0],
                "max": self.ranges[p.index][1],
                "has_range": p.has_range,
                "value": self.values[p.index],
                "source": p.source,
            }
            for p in self.table.params
        ]


def _number(name: str, value: Any) -> float:
    # bool is an int to Python: "true" for a gain is a mistake, not 1.0.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Invalid(f"parameter {name}: {value!r} is not a number")
    v = float(value)
    if not math.isfinite(v):
        raise Invalid(f"parameter {name}: {value!r} is not a finite number")
    return v


class ParamsService(RunObserver):
    name = "live tuning"

    def __init__(self, settings: Settings, supervisor: Supervisor, hub: Hub) -> None:
        self.settings = settings
        self.supervisor = supervisor
        self.hub = hub
        self.folder = settings.data_dir / "params"
        self.current: RunParams | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    # ---- run observer ----------------------------------------------------------------------

    def on_started(self, run: Run) -> None:
        ch = run.channels
        if ch is None:
            return
        try:
            table = chparams.read_table(ch.shm, ch.name)
        except ChannelsCorrupt as exc:
            if run.report_corrupt is not None:
                run.report_corrupt(exc)
            return
        values = chparams.read_values(ch.shm, table)
        ranges = [(p.min, p.max) if p.has_range else proposed_range(p.default) for p in table.params]
        self.current = RunParams(
            run_id=run.row.id,
            owner=run.row.owner or "",
            table=table,
            values=values,
            ranges=ranges,
            by_name={p.name: p.index for p in table.params},
        )
        self.hub.publish(self._message(self.current, "table"))
        self._apply_saved(run, self.current)

    # ---- saved parameters ----------------------------------------------------------------------

    def saved_values(self, folder: Path) -> dict[str, Any]:
        """The values of a project's saved-parameters file ({} when it has none). Bounded read,
        no link followed: the project folder holds what its owner uploaded."""
        try:
            fd = os.open(folder / SAVED_FILE, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
        except OSError:
            return {}
        with open(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                return {}
            data = f.read(SAVED_MAX_BYTES + 1)
        if len(data) > SAVED_MAX_BYTES:
            log.warning("%s: over %d bytes; not applied", SAVED_FILE, SAVED_MAX_BYTES)
            return {}
        try:
            doc = json.loads(data)
        except ValueError as exc:
            log.warning("%s: not JSON (%s); not applied", SAVED_FILE, exc)
            return {}
        values = doc.get("parameters") if isinstance(doc, dict) else None
        return values if isinstance(values, dict) else {}

    def _apply_saved(self, run: Run, rp: RunParams) -> None:
        """A run of a project with saved parameters starts with them: written now, before any
        command, so the loop takes them in IDLE, before INITIALISING (and, for 20-sim, again after
        its Initialize()). Names or values the controller no longer takes are left out, logged."""
        ch = run.channels
        saved = self.saved_values(Path(run.build.path)) if ch is not None and rp.table.params else {}
        entries: list[tuple[int, float]] = []
        for name, value in saved.items():
            try:
                one, _ = self._checked(rp, {name: value}, {})
            except XrfError as exc:
                log.warning("%s: %s; left out", SAVED_FILE, exc)
                continue
            entries += one
        if not entries or ch is None:
            return
        with rp.lock:
            seq = chparams.send_set(ch.shm, entries[: chparams.SET_MAX])

        async def confirm() -> None:
            answer = await asyncio.to_thread(chparams.wait_answer, ch.shm, seq, ANSWER_TIMEOUT_S * 5)
            if answer is None or not answer.applied:
                log.warning("run %s: the loop did not take the saved parameters", rp.run_id)
                return
            await self._applied(rp, entries, answer.cycle, SAVED_BY)

        task = asyncio.get_running_loop().create_task(confirm(), name="params-saved")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _applied(
        self, rp: RunParams, entries: list[tuple[int, float]], cycle: int, who: str
    ) -> list[ParamChange]:
        changes = []
        for i, v in entries:
            changes.append(ParamChange(name=rp.table.params[i].name, old=rp.values[i], new=v))
            rp.values[i] = v
        rp.changes += len(changes)
        rows = await asyncio.to_thread(self._log, rp, cycle, who, changes)
        # The run's live rerun recording shows them as text log entries (logs/rerun_live.py).
        run = self.supervisor.current
        live = run.logging.live if run is not None and run.row.id == rp.run_id and run.logging else None
        if live is not None:
            live.param_changes(rows)
        self.hub.publish(self._message(rp, "applied", cycle=cycle, who=who, changes=changes))
        return changes

    async def on_ended(self, row: RunRow, run: Run | None) -> None:
        if self.current is not None and self.current.run_id == row.id:
            self.current = None

    # ---- queries -----------------------------------------------------------------------------

    def _message(self, rp: RunParams | None, event: str, **extra: Any) -> ParamsMessage:
        origin = rp.table.origin if rp else "none"
        note = ""
        if rp is None:
            note = "no run is active"
        elif not rp.table.params:
            note = NO_PARAMS_NOTE[origin]
        return ParamsMessage(
            event=event,
            run_id=rp.run_id if rp else None,
            params=rp.describe() if rp else [],
            origin=origin,
            note=note,
            **extra,
        )

    def saved_file(self) -> dict[str, Any]:
        """The current values as the saved-parameters file's text (for "save as the project's
        parameters": the client saves it as the project's next version through the editor)."""
        rp = self.current
        if rp is None:
            raise Conflict("no run is active; start one first")
        if not rp.table.params:
            raise Conflict(NO_PARAMS_NOTE[rp.table.origin])
        doc = {
            "about": "tunable parameters a run of this project starts with (docs/students/tuning.md)",
            "parameters": {p.name: rp.values[p.index] for p in rp.table.params},
        }
        return {"path": SAVED_FILE, "content": json.dumps(doc, indent=2) + "\n"}

    def snapshot(self) -> list[ParamsMessage]:
        """For a browser that connects: the current table (the hub's snapshot source)."""
        return [self._message(self.current, "table")]

    def listing(self) -> dict[str, Any]:
        return self._message(self.current, "table").model_dump()

    def get(self, name: str) -> dict[str, Any]:
        rp = self.current
        if rp is None:
            raise Conflict("no run is active; start one first")
        i = rp.by_name.get(name)
        if i is None:
            raise NotFound(f"the controller has no parameter '{name}'{self._known(rp)}")
        return rp.describe()[i]

    @staticmethod
    def _known(rp: RunParams) -> str:
        names = list(rp.by_name)
        if not names:
            return f" ({NO_PARAMS_NOTE[rp.table.origin]})"
        return f" (it has: {', '.join(names[:20])}{', ...' if len(names) > 20 else ''})"

    # ---- a set --------------------------------------------------------------------------------

    def _checked(
        self, rp: RunParams, values: dict[str, Any], ranges: dict[str, Any]
    ) -> tuple[list[tuple[int, float]], dict[int, tuple[float, float]]]:
        if not isinstance(values, dict) or not values:
            raise Invalid("a set names at least one parameter")
        if len(values) > chparams.SET_MAX:
            raise Invalid(f"a set holds at most {chparams.SET_MAX} parameters")
        new_ranges: dict[int, tuple[float, float]] = {}
        for name, span in (ranges or {}).items():
            i = rp.by_name.get(name)
            if i is None:
                raise Invalid(f"unknown parameter '{name}'{self._known(rp)}")
            if rp.table.params[i].has_range:
                raise Invalid(
                    f"parameter {name}: its range is the controller's ({rp.ranges[i][0]:g} .. {rp.ranges[i][1]:g})"
                )
            if not isinstance(span, (list, tuple)) or len(span) != 2:
                raise Invalid(f"parameter {name}: a range is [min, max]")
            lo, hi = _number(name, span[0]), _number(name, span[1])
            if lo > hi:
                raise Invalid(f"parameter {name}: range min {lo:g} is above max {hi:g}")
            new_ranges[i] = (lo, hi)
        entries: list[tuple[int, float]] = []
        for name, value in values.items():
            i = rp.by_name.get(name)
            if i is None:
                raise Invalid(f"unknown parameter '{name}'{self._known(rp)}")
            v = _number(name, value)
            lo, hi = new_ranges.get(i, rp.ranges[i])
            if not lo <= v <= hi:
                hint = "" if rp.table.params[i].has_range else " (widen its range to go further)"
                raise Invalid(f"parameter {name}: {v:g} is out of range {lo:g} .. {hi:g}{hint}")
            entries.append((i, v))
        return entries, new_ranges

    async def set(self, values: dict[str, Any], who: str, ranges: dict[str, Any] | None = None) -> dict[str, Any]:
        """Apply `values` (name -> number) as one set; returns the cycle it landed at and the
        changes. Invalid/NotFound/Unavailable/Conflict with nothing applied."""
        run = self.supervisor.current
        rp = self.current
        if run is None or rp is None or rp.run_id != run.row.id or run.ended.is_set() or not run.alive:
            raise Conflict("no loop is running: parameters are set on a running controller")
        ch = run.channels
        if ch is None:
            raise Unavailable("the run is still starting")
        entries, new_ranges = self._checked(rp, values, ranges or {})
        if rp.changes >= CHANGES_MAX:
            raise Conflict(f"this run has logged {CHANGES_MAX} parameter changes; start a new run")

        def write_and_wait() -> chparams.Answer | None:
            with rp.lock:  # one set at a time on this block: the next waits for this one's answer
                t0 = time.monotonic()
                try:
                    seq = chparams.send_set(ch.shm, entries)
                except BlockingIOError:
                    raise Conflict("the loop's parameter block is held; try again") from None
                answer = chparams.wait_answer(ch.shm, seq, ANSWER_TIMEOUT_S)
                confirm_ms[0] = (time.monotonic() - t0) * 1000.0
                return answer

        confirm_ms = [0.0]
        answer = await asyncio.to_thread(write_and_wait)
        if answer is None:
            raise Unavailable(f"the loop did not take the set within {ANSWER_TIMEOUT_S:g} s (is it cycling?)")
        if not answer.applied:
            raise Conflict("the loop refused the set (it does not know one of the parameters); nothing applied")
        rp.ranges = [new_ranges.get(i, r) for i, r in enumerate(rp.ranges)]
        changes = await self._applied(rp, entries, answer.cycle, who)
        return {
            "cycle": answer.cycle,
            "confirm_ms": round(confirm_ms[0], 3),  # the set written -> the loop's answer read
            "changes": [c.model_dump() for c in changes],
            "params": rp.describe(),
        }

    # ---- the change log ---------------------------------------------------------------------

    def changes_file(self, run_id: int) -> Path:
        return self.folder / f"run-{int(run_id)}.jsonl"

    def _log(self, rp: RunParams, cycle: int, who: str, changes: list[ParamChange]) -> list[dict[str, Any]]:
        """Appends the changes to the run's change log; returns them as its rows."""
        self.folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        t = time.time()
        rows = [
            {"run": rp.run_id, "cycle": cycle, "t": t, "name": c.name, "old": c.old, "new": c.new, "who": who}
            for c in changes
        ]
        fd = os.open(self.changes_file(rp.run_id), os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o600)
        with open(fd, "a", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(row) + "\n")
        return rows

    def changes(self, run_id: int) -> list[dict[str, Any]]:
        """Every logged change of a run (empty: none)."""
        path = self.changes_file(run_id)
        if not path.is_file():
            return []
        out = []
        with open(path, encoding="utf-8") as f:
            for line in f:
                try:
                    out.append(json.loads(line))
                except ValueError:
                    continue  # a line cut by a crash: the others stand
        return out


def params_of(conn: HTTPConnection) -> ParamsService:
    """FastAPI dependency: the app's parameter service (made in server/app.py's lifespan)."""
    svc: ParamsService = conn.app.state.params
    return svc
