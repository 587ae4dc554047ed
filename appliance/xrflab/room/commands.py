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
"""

from __future__ import annotations

import asyncio
import logging
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


class CommandHandler:
    def __init__(self, services: BenchServices, link: CollectionTarget, loop: asyncio.AbstractEventLoop) -> None:
        self.services = services
        self.link = link
        self.loop = loop
        self.publisher: BenchPublisher | None = None
        self._seen = Recent()
        self._tasks: set[asyncio.Task[Any]] = set()

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
