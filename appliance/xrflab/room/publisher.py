"""A bench's voice in the room: retained status, a last will, and events that survive an outage.

One more observer of the run life cycle (`RoomRunObserver`: runs started and ended, from the run
record), and a listener of the appliance's hub (``hub.listeners``: state, alarms, lease,
self-check, as the dashboards get them, as typed messages), without a wire of its own into the
supervisor; `facts` (bench.py) is asked once a second for what no message carries (cycles,
misses, CPU temperature, disk).

Every payload is a model of payloads.py, built here with its bounds (``Model.build``) and parsed
there by the room; what the room sends (commands, the class list, assignments) is parsed here the
same way, and whatever does not fit is dropped and logged, never acted on.

- ``xrf/bench/<name>/online`` (payloads.Online): true with ``conn`` = (boot, n) on every connect;
  the same topic with false is the MQTT last will the broker publishes when the bench goes silent
  (power, network, crash). `conn` tells the room which connection a will belongs to: the will of
  an older connection never marks a reconnected bench offline.
- ``xrf/bench/<name>/status`` (retained, payloads.Status): the whole status, on every change (at
  most ``MAX_STATUS_HZ``) and every second. Statuses are never queued: only the newest is worth
  sending, and it carries (boot, seq) so a late or duplicated one does not overwrite a newer one.
  It says nothing about where the bench is: the room links to the address recorded at enrolment.
- ``xrf/bench/<name>/event`` (QoS 1, payloads.Event): alarms, run started/ended, self-check
  verdicts, assignments received. Kept in a bounded queue until the broker acknowledges each (an
  outage loses nothing up to ``queue_max`` events; beyond, the oldest go and ``events_dropped``
  says how many), resent after reconnecting, sent only while the room says it listens
  (``xrf/room/online``). The room drops duplicates by (boot, seq).

paho's network thread calls our callbacks; the appliance's state is touched only on its event
loop (``call_soon_threadsafe``).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..server.runs.lifecycle import RunObserver
from ..server.ws.messages import AlarmMessage, LeaseMessage, SelfcheckMessage, ServerMessage, StateMessage
from . import mqtt, payloads, topics
from .payloads import MAX_ALARMS, Malformed, safe_text

if TYPE_CHECKING:
    from ..server.runs.run import Run
    from ..server.runs.store import RunRow

log = logging.getLogger(__name__)

MAX_STATUS_HZ = 20.0
HEARTBEAT_S = 1.0


def next_boot(folder: Path) -> int:
    """A number that grows with every appliance start, even if the clock went back (a Pi has no
    battery clock): max(last + 1, now in ms), kept in <folder>/boot."""
    path = folder / "boot"
    try:
        last = int(path.read_text().strip())
    except (OSError, ValueError):
        last = 0
    boot = max(last + 1, time.time_ns() // 1_000_000)
    folder.mkdir(parents=True, exist_ok=True)
    path.write_text(f"{boot}\n")
    return boot


class BenchPublisher:
    def __init__(
        self,
        name: str,
        endpoint: mqtt.Endpoint,
        boot: int,
        facts: Callable[[], dict[str, Any]] = dict,
        queue_max: int = 1000,
        on_command: Callable[[payloads.Command | payloads.CommandHead, float], None] | None = None,
        on_accounts: Callable[[payloads.ClassList], None] | None = None,
        on_assignment: Callable[[payloads.Assignment], None] | None = None,
    ) -> None:
        self.name = topics.check_bench_name(name)
        self.endpoint = endpoint
        self.boot = boot
        self.facts = facts
        self.on_command = on_command
        self.on_accounts = on_accounts
        self.on_assignment = on_assignment
        self.drops = payloads.Drops(f"bench {self.name}")
        self.seq = 0
        self.conn = 0
        self.connected = False
        self.room_listens = False  # xrf/room/online (payloads.RoomOnline): events wait until true
        self.status: dict[str, Any] = {
            "state": "NO RUN",
            "run_id": None,
            "run_owner": "",
            "holder": "",
            "alarms": [],
            "selfcheck": None,
            "message": "",
            "assignments": [],
        }
        self._events: deque[tuple[int, bytes]] = deque()
        self._inflight: dict[int, int] = {}  # paho mid -> event seq
        self.queue_max = queue_max
        self.events_dropped = 0
        self._lock = threading.Lock()  # events and seq: written from the loop and paho's thread
        self._last_status_t = 0.0
        self._status_pending: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._heartbeat: asyncio.Task[None] | None = None
        self._client = mqtt.client(endpoint, f"bench-{self.name}", will=self._will())
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.on_publish = self._on_publish
        self._client.on_message = self._on_message

    # -- life -----------------------------------------------------------------------------------
    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        mqtt.connect_async(self._client, self.endpoint)
        self._client.loop_start()
        self._heartbeat = self._loop.create_task(self._beat(), name="room-heartbeat")

    async def stop(self) -> None:
        """A clean goodbye: offline now (a disconnect on purpose sends no will)."""
        if self._heartbeat:
            self._heartbeat.cancel()
        if self.connected:
            info = self._client.publish(
                topics.bench(self.name, "online"), self._online(False, self.conn), qos=1, retain=True
            )
            await asyncio.get_running_loop().run_in_executor(None, lambda: info.wait_for_publish(1.0))
        self._client.disconnect()
        self._client.loop_stop()

    async def _beat(self) -> None:
        while True:
            await asyncio.sleep(HEARTBEAT_S)
            try:
                self.publish_status()
            except Exception:
                log.exception("room status")

    # -- what the bench says --------------------------------------------------------------------
    def _online(self, online: bool, conn: int) -> bytes:
        return payloads.Online.make(online=online, conn=(self.boot, conn)).wire()

    def _will(self) -> tuple[str, bytes]:
        return topics.bench(self.name, "online"), self._online(False, self.conn + 1)

    def _next_seq(self) -> int:
        with self._lock:
            self.seq += 1
            return self.seq

    def snapshot(self) -> payloads.Status:
        facts: dict[str, Any] = {}
        try:
            facts = self.facts()
        except Exception:
            log.exception("room facts")
        with self._lock:
            queued = len(self._events)
        return payloads.Status.make(
            **{
                **self.status,
                **facts,
                "boot": self.boot,
                "seq": self._next_seq(),
                "t": time.time(),
                "events_queued": queued,
                "events_dropped": self.events_dropped,
            }
        )

    def publish_status(self) -> None:
        self._last_status_t = time.monotonic()
        if self._status_pending is not None:
            self._status_pending.cancel()
            self._status_pending = None
        if not self.connected:
            return  # never queued: the next connect publishes the newest
        self._client.publish(topics.bench(self.name, "status"), self.snapshot().wire(), qos=1, retain=True)

    def status_changed(self) -> None:
        """Publish soon: at once, or after the rate limit's gap (changes in between coalesce)."""
        if self._loop is None or self._status_pending is not None:
            return
        wait = self._last_status_t + 1.0 / MAX_STATUS_HZ - time.monotonic()
        if wait <= 0:
            self.publish_status()
        else:
            self._status_pending = self._loop.call_later(wait, self.publish_status)

    def event(self, kind: str, /, **fields: Any) -> None:
        seq = self._next_seq()
        try:
            data = payloads.build_event(kind, **fields, boot=self.boot, seq=seq, t=time.time()).wire()
        except (TypeError, ValueError):  # a sender out of step with payloads.py: said, not sent
            log.exception("room event %s", kind)
            return
        with self._lock:
            if len(self._events) >= self.queue_max:
                self._events.popleft()
                self.events_dropped += 1
            self._events.append((seq, data))
        self._flush()

    def _flush(self) -> None:
        """Send every queued event not in flight (paho's thread or the loop: both may call).
        Only while the room listens: the broker acknowledges a QoS 1 message nobody subscribed to,
        and after a broker restart the bench is often back before the room (payloads.RoomOnline)."""
        if not (self.connected and self.room_listens):
            return
        with self._lock:
            flying = set(self._inflight.values())
            todo = [(s, d) for s, d in self._events if s not in flying]
        for seq, data in todo:
            info = self._client.publish(topics.bench(self.name, "event"), data, qos=1)
            if info.rc == 0:
                with self._lock:
                    self._inflight[info.mid] = seq

    # -- the run life cycle (the appliance's event loop) ----------------------------------------
    def run_started(self, row: RunRow) -> None:
        s = self.status
        s.update(run_id=row.id, run_owner=row.owner, alarms=[])
        self.event("run_started", run_id=row.id, owner=row.owner, build=safe_text(row.build, 128))
        self.status_changed()

    def run_ended(self, row: RunRow) -> None:
        self.status.update(run_id=row.id, run_owner=row.owner)
        self.event(
            "run_ended",
            run_id=row.id,
            owner=row.owner,
            end_reason=safe_text(row.end_reason, 32),
            cycles=row.cycles,
            misses=row.misses,
        )
        self.status_changed()

    # -- hub listener (the appliance's event loop) ----------------------------------------------
    def on_hub(self, message: ServerMessage) -> None:
        """Every message the dashboards get, as its typed model (server/ws/messages.py): a renamed field
        fails the type check here instead of silently stopping the room's view of the bench."""
        s = self.status
        if isinstance(message, StateMessage):
            changed = s.get("state") != message.name
            s["state"] = message.name
            if changed:
                self.status_changed()
        elif isinstance(message, AlarmMessage):
            if message.kind == "room":
                return  # our own message to the dashboards, not the bench's
            alarm = {"kind": message.kind, "message": safe_text(message.message, 300), "t": time.time()}
            s["alarms"] = [*s.get("alarms", []), alarm][-MAX_ALARMS:]
            self.event("alarm", alarm=alarm["kind"], message=alarm["message"], run_id=message.run_id)
            self.status_changed()
        elif isinstance(message, LeaseMessage):
            s["holder"] = message.holder.username if message.holder is not None else ""
            self.status_changed()
        elif isinstance(message, SelfcheckMessage) and message.event == "report":
            # The checker's own fields are extra fields of the model (messages.SelfcheckMessage).
            extra = message.model_extra or {}
            report = extra.get("report") or {}
            verdict = report.get("verdict") or ("error" if extra.get("message") else "")
            verdict = safe_text(verdict, 32)
            name = safe_text(extra.get("name", ""), 128)
            s["selfcheck"] = {
                "verdict": verdict,
                "t": time.time(),
                "check": message.check,
                "report": name,
                "message": safe_text(extra.get("message", ""), 300),
            }
            self.event("selfcheck", verdict=verdict, check=message.check, report=name)
            self.status_changed()

    # -- paho's thread --------------------------------------------------------------------------
    def _on_connect(self, client: Any, _userdata: Any, _flags: Any, reason: Any, _props: Any = None) -> None:
        if not mqtt.reason_ok(reason):
            log.warning("room broker refused bench %s: %s", self.name, reason)
            return
        self.conn += 1
        self.connected = True
        client.subscribe(
            [
                (topics.cmd(self.name), 1),
                (topics.CMD_ALL, 1),
                (topics.ACCOUNTS, 1),
                (topics.ASSIGNMENTS, 1),
                (topics.ROOM_ONLINE, 1),
            ]
        )
        client.publish(topics.bench(self.name, "online"), self._online(True, self.conn), qos=1, retain=True)
        # the will the broker keeps now is this connection's; the next connect's must name the next
        client.will_set(*self._will(), qos=1, retain=True)
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self.publish_status)
        with self._lock:
            self._inflight.clear()
        self._flush()

    def _on_disconnect(self, _client: Any, _userdata: Any, _flags: Any, _reason: Any, _props: Any = None) -> None:
        self.connected = False
        self.room_listens = False  # the retained RoomOnline says it again on the next connect
        with self._lock:
            self._inflight.clear()  # unacknowledged: sent again on the next connect

    def _on_publish(self, _client: Any, _userdata: Any, mid: int, reason: Any, _props: Any = None) -> None:
        with self._lock:
            seq = self._inflight.pop(mid, None)
            if seq is not None and mqtt.reason_ok(reason):
                # acknowledged: out of the queue (it is ordered by seq; acks may come in any order)
                self._events = deque((s, d) for s, d in self._events if s != seq)

    def _on_message(self, _client: Any, _userdata: Any, msg: Any) -> None:
        """The room's messages, each parsed by its model (payloads.py) before anything acts on it;
        a malformed one is dropped and logged. An empty payload clears a retained message: nothing."""
        t_recv = time.time()
        topic, data = str(msg.topic), msg.payload
        if not data:
            return
        limit = payloads.ROOM_MAX_BYTES
        try:
            if topic == topics.ROOM_ONLINE:
                self.room_listens = payloads.parse(payloads.ROOM_ONLINE, data, limit).online
                self._flush()
            elif topic == topics.ACCOUNTS:
                accounts = payloads.parse(payloads.CLASS_LIST, data, limit)
                if self.on_accounts is not None and self._loop is not None:
                    self._loop.call_soon_threadsafe(self.on_accounts, accounts)
            elif topic.startswith(topics.assignment("")):
                assignment = payloads.parse(payloads.ASSIGNMENT, data, limit)
                if topic != topics.assignment(assignment.id):
                    raise Malformed(f"the assignment {assignment.id} on another's topic")
                if self.on_assignment is not None and self._loop is not None:
                    self._loop.call_soon_threadsafe(self.on_assignment, assignment)
            elif topic in (topics.cmd(self.name), topics.CMD_ALL):
                command: payloads.Command | payloads.CommandHead
                try:
                    command = payloads.parse(payloads.COMMAND, data, payloads.BENCH_MAX_BYTES)
                except Malformed as exc:
                    # answered when it says who asked (its id): "not understood", then dropped
                    command = payloads.parse(payloads.COMMAND_HEAD, data, payloads.BENCH_MAX_BYTES)
                    self.drops.drop("room", topic, str(exc))
                if self.on_command is not None:
                    self.on_command(command, t_recv)  # called here: stop must not wait for the loop's queue
        except Malformed as exc:
            self.drops.drop("room", topic, str(exc))

    def reply(self, **fields: Any) -> None:
        """Answer a command (payloads.Reply); one that does not fit is logged, never sent half."""
        try:
            data = payloads.Reply.make(**fields).wire()
        except (TypeError, ValueError):
            log.exception("room reply %s", fields.get("cmd"))
            return
        if self.connected:
            self._client.publish(topics.bench(self.name, "reply"), data, qos=1)

    def grades(self, **fields: Any) -> bool:
        """A grading table (payloads.Grades) to the room, if connected now: not queued, the room
        asks again (its page's refresh) and the newest table is all it wants."""
        try:
            data = payloads.Grades.make(**fields, boot=self.boot, seq=self._next_seq(), t=time.time()).wire()
        except (TypeError, ValueError):
            log.exception("room grades %s", fields.get("assignment"))
            return False
        if len(data) > payloads.GRADES_MAX_BYTES:  # commands.grades_fields cuts rows to fit: a bug if not
            log.error("room grades %s: %d bytes, not sent", fields.get("assignment"), len(data))
            return False
        if not self.connected:
            return False
        self._client.publish(topics.bench(self.name, "grades"), data, qos=1)
        return True


class Recent(OrderedDict[Any, None]):
    """The last `size` keys seen, oldest out first: a bounded memory of ids (commands.py) and of
    (boot, seq) of events (the room's), which a sender cannot grow."""

    def __init__(self, size: int = 256) -> None:
        super().__init__()
        self.size = size

    def seen(self, key: Any) -> bool:
        if key in self:
            return True
        self[key] = None
        if len(self) > self.size:
            self.popitem(last=False)
        return False


class RoomRunObserver(RunObserver):
    """The bench publisher's place in the run life cycle (server/runs/lifecycle.py): runs started and
    ended reach the room from the run record, not from the dashboards' run message."""

    name = "room"

    def __init__(self, publisher: BenchPublisher) -> None:
        self.publisher = publisher

    def on_started(self, run: Run) -> None:
        self.publisher.run_started(run.row)

    async def on_ended(self, row: RunRow, run: Run | None) -> None:
        self.publisher.run_ended(row)
