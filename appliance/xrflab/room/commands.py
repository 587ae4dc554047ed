"""What a bench does with the room's commands (``xrf/cmd/<name>`` and ``xrf/cmd/all``).

Only the room may publish there (the broker's ACL), so a command needs no further login; who in
the room asked is in ``by`` and goes to the bench's audit trail as ``room.<cmd>``. Each arrives
parsed by its model (payloads.Command: the fields and bounds of each command); one that does not
parse is answered ``ok: false`` when its id can be read, and otherwise only logged. Every command
is answered on ``xrf/bench/<name>/reply`` with its ``id``, the wall-clock time it arrived
(``t_recv``) and the time it was done (``t_done``: for ``stop``, when the loop accepted it), which
is what the room and the benchmark measure.

- ``stop``: the loop's own ``stop`` command (the state machine's safe stop, as the STOP button),
  handed to the appliance's event loop at once from paho's thread.
- ``message``: ``text`` shown on the bench's dashboards (an ``alarm`` of kind ``room``: the alarm
  bar every page has).
- ``selfcheck``: the FPGA self-check with ``profile``, on an idle bench only (a run is never
  stopped for it); the verdict comes back in the status and as a ``selfcheck`` event. A bench
  with a run going answers ``skipped: busy`` and shows the verdict ``skipped`` in its status.
- ``collect``: the runs of the projects made from ``assignment`` packed and uploaded to the room
  (collect.py); the reply says how many runs and bytes.
- ``grades``: the bench's grading table of ``assignment`` (its own students' latest results, its
  own grading service: grading/service.py) sent on ``xrf/bench/<name>/grades``; with ``scenario``
  it keeps that scenario first, with ``rerun`` it grades every student's latest build (its queue,
  bounded parallel) and sends the table every ``GRADES_EVERY_S`` until the queue is through. The
  reply says how many rows, or why none (no scenario, not this bench's assignment, a scenario
  refused with its line).
"""

from __future__ import annotations

import asyncio
import logging
import math
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ..errors import XrfError
from ..server.ws.messages import AlarmMessage
from . import payloads
from .payloads import safe_text
from .publisher import BenchPublisher, Recent

if TYPE_CHECKING:
    from .services import BenchServices


class CollectionTarget(Protocol):
    """Where a collection's archive goes: the bench's room link (bench.py's RoomLink)."""

    name: str
    folder: Path

    def upload_collection(self, cid: str, archive: Path) -> None: ...


log = logging.getLogger(__name__)

GRADES_EVERY_S = 1.0  # the table while a re-run goes on (the room page's progress)
GRADES_WATCH_MAX_S = 3600.0  # a re-run watched longer than this: the room asks again when it wants


def grades_fields(grading: Any, aid: str) -> dict[str, Any]:
    """The bench's table of `aid` as payloads.Grades' fields: text cut to its bounds, numbers the
    model refuses (NaN, infinity) left out, rows cut to fit ``GRADES_MAX_BYTES`` (``left_out``
    says how many did not). Blocking (the results are files)."""
    try:
        t = grading.table(aid)
    except XrfError as exc:  # no scenario, no such assignment here
        return {"assignment": aid, "error": safe_text(exc, 300)}
    checks = [payloads.GradeCheck.make(id=c["id"], kind=c["kind"], points=c["points"]) for c in t["checks"]]
    rows: list[payloads.GradeRow] = []
    left_out = 0
    for r in t["rows"]:
        try:
            rows.append(
                payloads.GradeRow.make(
                    project=r["project"],
                    owner=r["owner"],
                    name=safe_text(r["name"], 128),
                    job=r["job"],
                    build=safe_text(r["build"] or "", 128),
                    status=r["status"],
                    reason=safe_text(r["reason"] or "", 300),
                    earned=r["earned"] or 0.0,
                    points=r["points"] or 0.0,
                    graded_at=r["graded_at"],
                    run=r["run"],
                    checks={
                        cid: {
                            "earned": c["earned"],
                            "passed": bool(c["passed"]),
                            "value": c["value"]
                            if isinstance(c["value"], int | float) and math.isfinite(c["value"])
                            else None,
                        }
                        for cid, c in r["checks"].items()
                    },
                )
            )
        except (TypeError, ValueError, KeyError):  # a result file out of step with the model: said, not sent
            log.exception("room grades %s: project %s", aid, r.get("project"))
            left_out += 1
    p = t["progress"]
    progress = payloads.GradeProgress.make(**{k: p[k] for k in ("parallel", "total", "queued", "running", "done")})
    room = payloads.GRADES_MAX_BYTES - 4096  # the envelope's share
    kept: list[payloads.GradeRow] = []
    size = sum(len(c.wire()) + 1 for c in checks)
    for row in rows[: payloads.MAX_GRADE_ROWS]:
        size += len(row.wire()) + 1
        if size > room:
            break
        kept.append(row)
    left_out += len(rows) - len(kept)
    return {"assignment": aid, "checks": checks, "rows": kept, "left_out": left_out, "progress": progress}


class CommandHandler:
    def __init__(self, services: BenchServices, link: CollectionTarget, loop: asyncio.AbstractEventLoop) -> None:
        self.services = services
        self.link = link
        self.loop = loop
        self.publisher: BenchPublisher | None = None
        self._seen = Recent()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._watching: dict[str, asyncio.Task[Any]] = {}  # assignment -> its re-run's table sender

    def __call__(self, command: payloads.Command | payloads.CommandHead, t_recv: float) -> None:
        """paho's thread: hand over to the event loop without waiting for anything else."""
        self.loop.call_soon_threadsafe(self._spawn, command, t_recv)

    def _spawn(self, command: payloads.Command | payloads.CommandHead, t_recv: float) -> None:
        if self._seen.seen(command.id):
            return  # QoS 1 may deliver twice
        task = self.loop.create_task(self._run(command, t_recv))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _run(self, command: payloads.Command | payloads.CommandHead, t_recv: float) -> None:
        cmd = command.cmd
        reply: dict[str, Any] = {"id": command.id, "cmd": cmd, "t_recv": t_recv}
        by = ""
        try:
            if isinstance(command, payloads.CommandHead):  # it did not parse as any command
                reply.update(ok=False, error=f"unknown or malformed command {cmd!r}")
            else:
                by = command.by
                reply["t_sent"] = command.t
                handler = getattr(self, f"_cmd_{cmd}")
                reply.update(await handler(command))
        except Exception as exc:  # any failure is an answer, never a dead bench
            log.exception("room command %s", cmd)
            reply.update(ok=False, error=safe_text(exc, 300))
        reply["t_done"] = time.time()
        from ..server.security import audit

        audit.record(None, f"room.{cmd}", {"by": by, "ok": reply.get("ok"), "id": command.id})
        if self.publisher is not None:
            self.publisher.reply(**reply)

    async def _cmd_stop(self, _command: payloads.Stop) -> dict[str, Any]:
        sup = self.services.supervisor
        run = sup.current
        if run is None or not run.alive:
            return {"ok": True, "accepted": None, "state": "NO RUN", "note": "no loop running"}
        result = await sup.command("stop")
        return {
            "ok": True,
            "accepted": result.accepted,
            "state": result.state_name,
            "reason": safe_text(result.reason, 300) if result.reason is not None else None,
            "t_loop": time.time(),
        }

    async def _cmd_message(self, command: payloads.Message) -> dict[str, Any]:
        text = command.text.strip()
        if not text:
            return {"ok": False, "error": "empty message"}
        by = command.by or "the room"
        # model_validate: the field's JSON name, "from", is a Python keyword (AlarmMessage.from_).
        alarm = AlarmMessage.model_validate({"kind": "room", "message": f"From {by} (the room): {text}", "from": by})
        self.services.supervisor.hub.publish(alarm)
        if self.publisher is not None:
            self.publisher.status["message"] = text
            self.publisher.status_changed()
        return {"ok": True}

    async def _cmd_selfcheck(self, command: payloads.Selfcheck) -> dict[str, Any]:
        from ..selfcheck_service import SelfCheckService, StartCheck
        from ..server.security.accounts import User

        sup = self.services.supervisor
        if sup.current is not None and sup.current.alive:
            why = "a run is active; the self-check runs on idle benches only"
            if self.publisher is not None:  # the tile says so, beside the others' verdicts
                self.publisher.status["selfcheck"] = {"verdict": "skipped", "t": time.time(), "message": why}
                self.publisher.status_changed()
            return {"ok": False, "skipped": "busy", "error": why}
        svc: SelfCheckService = self.services.selfcheck  # the appliance's, made at start-up (server/app.py)
        who = User(id=0, username=f"room:{command.by[:32]}", role="educator")
        try:
            active = await svc.start(StartCheck(profile=command.profile), who, "room")
        except XrfError as exc:  # what the route would answer (its body's detail) is the reply's error
            return {"ok": False, "error": safe_text(exc.body()["detail"], 300)}
        return {"ok": True, "check": active.id}

    async def _cmd_collect(self, command: payloads.Collect) -> dict[str, Any]:
        from ..projects.assignments import origin
        from ..projects.service import ProjectsService
        from .collect import RunToPack, pack_bench

        link = self.link
        aid, cid = command.assignment, command.collection
        formats: list[str] = sorted(set(command.formats))
        svc: ProjectsService = self.services.projects  # the appliance's, made at start-up (server/app.py)
        runs_store = self.services.supervisor.store
        runs: list[RunToPack] = []
        for p in svc.store.projects_with_origin(origin(aid)):  # every student's copy, on this bench
            for ln in svc.store.runs_of(p.id):
                row = runs_store.get(ln["run_id"])
                if row is not None:
                    runs.append(
                        RunToPack(p.owner, {"id": p.id, "name": p.name}, ln["build_id"], row.as_dict(), row.run_dir)
                    )
        folder = link.folder
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder, prefix="collect-") as tmp:
            out = Path(tmp) / "runs.tar.gz"
            manifest = await asyncio.to_thread(pack_bench, link.name, aid, runs, formats, out)
            size = out.stat().st_size
            await asyncio.to_thread(link.upload_collection, cid, out)
        return {"ok": True, "runs": len(manifest["runs"]), "bytes": size, "left_out": len(manifest["left_out"])}

    async def _cmd_grades(self, command: payloads.Grade) -> dict[str, Any]:
        grading = self.services.grading
        aid = command.assignment
        try:
            if command.scenario is not None:  # a ScenarioError (with its line) is the reply's error
                grading.set_scenario(aid, command.scenario)
            if command.rerun:
                grading.rerun_all(aid)
        except XrfError as exc:  # refused, as the bench's own route would: said, not logged as a fault
            fields = {"assignment": aid, "error": safe_text(exc, 300)}
            if self.publisher is not None:
                self.publisher.grades(**fields)
            return {"ok": False, "error": fields["error"]}
        fields = await asyncio.to_thread(grades_fields, grading, aid)
        if self.publisher is not None:
            self.publisher.grades(**fields)
        if command.rerun and aid not in self._watching:
            task = self.loop.create_task(self._send_while_grading(aid))
            self._watching[aid] = task
            task.add_done_callback(lambda _t: self._watching.pop(aid, None))
        if fields.get("error"):
            return {"ok": False, "error": fields["error"]}
        return {"ok": True, "graded": len(fields["rows"])}

    async def _send_while_grading(self, aid: str) -> None:
        """The table every GRADES_EVERY_S while this assignment's jobs are queued or running, and
        once more when they are through (the room's progress bar and final rows)."""
        deadline = time.monotonic() + GRADES_WATCH_MAX_S
        while time.monotonic() < deadline:
            await asyncio.sleep(GRADES_EVERY_S)
            fields = await asyncio.to_thread(grades_fields, self.services.grading, aid)
            if self.publisher is not None:
                self.publisher.grades(**fields)
            p = fields.get("progress")
            if p is None or (p.queued == 0 and p.running == 0):
                return
