"""WebSocket fan-out: one producer (the run's reader task) to many browsers, none able to slow
the others down.

Every message is encoded to JSON once and the same string is queued for each client, so 30
clients cost 30 queue appends, not 30 encodings. Each client has its own bounded queue and its
own sender task (`Client.pump`): a browser that reads slowly only fills its own queue. A client
whose queue is empty and whose socket takes a write at once gets a message sent by the publisher
itself (`Client.deliver`), without a wake-up of its sender task per message; a send that would
wait (the socket's buffer full) finishes on its own and what follows queues behind it. Telemetry is the only
topic that is allowed to be lossy (a newer sample supersedes an older one), so a full telemetry
queue drops its oldest entry and counts it; everything else (state, alarms, run events, errors,
monitor lines) is kept, and a client whose queue grows past a hard limit, or that has been
losing telemetry continuously for `slow_client_s`, is disconnected.

Not every message is everyone's: `Hub.scope` (ownership.scope, set by ownership.attach) names
a message's owner and what other clients receive instead; the full text goes to clients whose
user `Hub.may_see` the owner, the public one (encoded once too) to the rest.

What the hub takes is typed: a model of server/ws/messages.py (`ServerMessage`), never a dict (but
for telemetry's wire fields, `publish_fields`, whose producer checks them against the model), so a message
is checked against the protocol where it is built and its sender's name is in the traceback. It
is turned into its wire fields once (`unpack`: the fields the sender set, as JSON values), which
the listeners, the scope rule and the encoder share.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple

import msgspec
from starlette.websockets import WebSocket

from .messages import SERVER, SERVER_KINDS, TOPICS, ReplyMessage, ServerMessage

__all__ = ["TOPICS", "Client", "ClientQueue", "Hub", "Scoped", "SlowClient", "encode", "unpack"]

LOSSY = "telemetry"
# `type` leads the encoded message (encode); the payload is everything else.
_NOT_PAYLOAD = {"type"}


def unpack(message: ServerMessage) -> tuple[str, dict[str, Any]]:
    """(kind, fields) of a message model: the fields its sender set (exclude_unset: a field left
    out stays absent, as the dicts the senders built before the models left it), JSON values,
    `from_` as `from`. Refuses anything but a server/ws/messages.py server model (TypeError)."""
    if not isinstance(message, SERVER):
        raise TypeError(f"the hub sends server/ws/messages.py models (ServerMessage), not {type(message).__name__}")
    return message.type, message.model_dump(mode="json", by_alias=True, exclude_unset=True, exclude=_NOT_PAYLOAD)


# msgspec's encoder (a dependency of viser's too): the same compact JSON as json.dumps with these
# separators, 5x quicker (3 against 16 us for a telemetry message), and NaN/inf as null, which is
# what browsers' JSON.parse needs (a controller computing NaN must not break the fan-out).
_JSON = msgspec.json.Encoder()


def encode(message_type: str, payload: dict[str, Any]) -> str:
    message = {"type": message_type, **payload}
    try:
        return _JSON.encode(message).decode()
    except (TypeError, ValueError, OverflowError):
        # Something msgspec does not take (a key that is not a string, say): the slow way, with
        # the same rule for non-finite floats.
        return json.dumps(_finite(message), separators=(",", ":"), allow_nan=False)


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


class Scoped(NamedTuple):
    """A message that belongs to someone: `owner` (a username, None = unknown: educators only)
    and what everyone else receives in its place (None: nothing), or a function that makes it:
    called only when a client that may not see the owner's part is there (telemetry, 30 a
    second: with only the owner and educators watching, no public copy is made; issue 30 item 4)."""

    owner: str | None
    public: dict[str, Any] | Callable[[], dict[str, Any]] | None


# A bug in the scope function must not hand a message to everyone: it goes to educators only.
_FAIL_CLOSED = Scoped(None, None)


class SlowClient(Exception):
    """The client cannot keep up and is being disconnected."""


class ClientQueue:
    """Two deques: lossy telemetry (drop-oldest) and everything else (kept, hard-capped)."""

    def __init__(self, max_telemetry: int, max_total: int, slow_after_s: float) -> None:
        self._telemetry: deque[str] = deque()
        self._other: deque[str] = deque()
        self._max_telemetry = max_telemetry
        self._max_total = max_total
        self._slow_after_s = slow_after_s
        self._ready = asyncio.Event()
        self.dropped = 0
        # monotonic time since which every telemetry put had to drop something; None = keeping up
        self._pressure_since: float | None = None

    def __len__(self) -> int:
        return len(self._telemetry) + len(self._other)

    def put(self, topic: str, text: str) -> None:
        """Queue a message; raises SlowClient when the client has to go."""
        if topic == LOSSY:
            if len(self._telemetry) >= self._max_telemetry:
                self._telemetry.popleft()
                self.dropped += 1
                now = time.monotonic()
                if self._pressure_since is None:
                    self._pressure_since = now
                elif now - self._pressure_since > self._slow_after_s:
                    raise SlowClient(
                        f"dropped telemetry for {now - self._pressure_since:.1f} s ({self.dropped} messages)"
                    )
            self._telemetry.append(text)
        else:
            if len(self._other) >= self._max_total:
                raise SlowClient(f"{len(self._other)} messages waiting")
            self._other.append(text)
        self._ready.set()

    def wake(self) -> None:
        """Ends a `wait` without a message (Client: its own send finished or failed)."""
        self._ready.set()

    async def wait(self) -> None:
        """Until the next put or wake (from now: what was put before does not end it)."""
        self._ready.clear()
        await self._ready.wait()

    async def get(self) -> str:
        while True:
            # Control messages first: a state change must not wait behind a backlog of samples.
            if self._other:
                return self._other.popleft()
            if self._telemetry:
                text = self._telemetry.popleft()
                if len(self._telemetry) <= self._max_telemetry // 2:
                    self._pressure_since = None  # drained to half: the client is keeping up
                return text
            self._ready.clear()
            await self._ready.wait()


class Client:
    def __init__(self, ws: WebSocket, queue: ClientQueue) -> None:
        self.ws = ws
        self.queue = queue
        self.topics: set[str] = set(TOPICS)
        self.kicked = asyncio.Event()
        self.kick_reason = ""
        self.user: Any = None  # the logged-in accounts.User (set by the /ws handler)
        # The last answer of the ownership rule for this client: (user, owner, may see). The rule
        # is a function of the two (User is frozen; a new login sets a new object), and the live
        # run's owner is the same for every message of a run: asked once, not 30 times a second.
        self._seen: tuple[Any, Any, bool] = (None, None, False)
        # The pump waits on an empty queue with no send under way: a message can go out at once
        # (deliver), in the publisher's turn of the event loop, instead of waking the pump for it.
        self._idle = False
        self._failed: BaseException | None = None  # a send made by deliver failed: the pump raises it
        self._finishing: asyncio.Task[None] | None = None  # a send by deliver that had to wait

    def sees(self, owner: str | None, rule: Callable[[Any, str | None], bool]) -> bool:
        """rule(self.user, owner) (Hub.may_see), remembered for the same user and owner."""
        user, last_owner, yes = self._seen
        if user is not self.user or last_owner != owner:
            yes = rule(self.user, owner)
            self._seen = (self.user, owner, yes)
        return yes

    def deliver(self, topic: str, text: str) -> None:
        if self.kicked.is_set() or self._failed is not None:
            return
        if self._idle and not self.queue and self._finishing is None:
            self._send_now(text)
            return
        try:
            self.queue.put(topic, text)
        except SlowClient as exc:
            self.kick_reason = str(exc)
            self.kicked.set()

    def _send_now(self, text: str) -> None:
        """Send `text` now, from the publisher's turn: nothing is queued or being sent, so the
        order is kept, and the pump is not woken for it (a telemetry message a wake-up of its
        own: a task switch and a turn of the event loop per message, 30 a second per dashboard,
        issue 30 item 4). The send (starlette, then uvicorn's protocol: a write to the socket's
        transport) only waits when the transport asked us to pause writing, its buffer full; then
        it is finished as a task, and what comes meanwhile is queued behind it."""
        coro = self.ws.send_text(text)
        try:
            waiting_on = coro.send(None)
        except StopIteration:
            return
        except Exception as exc:  # the socket is gone: the pump ends the connection with it
            self._fail(exc)
            return
        self._finishing = asyncio.ensure_future(self._finish(coro, waiting_on))

    async def _finish(self, coro: Any, waiting_on: Any) -> None:
        """Run a send that `_send_now` started and that stopped at an await to its end, as a task
        would: wait for what it waits on, then resume it (its result or exception)."""
        try:
            while True:
                try:
                    if waiting_on is None:  # a bare yield: the event loop's next turn
                        await asyncio.sleep(0)
                    else:
                        # What a task does with a future its coroutine yielded: take it over
                        # (the flag says "yielded, not yet taken"; awaiting it again refuses it).
                        waiting_on._asyncio_future_blocking = False
                        await waiting_on
                except BaseException as exc:  # noqa: BLE001  # handed to the send, as a task would
                    waiting_on = coro.throw(exc)
                else:
                    waiting_on = coro.send(None)
        except StopIteration:
            pass
        except Exception as exc:
            self._fail(exc)
        finally:
            coro.close()
            self._finishing = None
            self.queue.wake()

    def stop(self) -> None:
        """The connection is over: a send of deliver's still waiting is cancelled."""
        if self._finishing is not None:
            self._finishing.cancel()

    def _fail(self, exc: BaseException) -> None:
        self._failed = exc
        self.queue.wake()

    def reply(self, message: ReplyMessage) -> None:
        """A message for this client only (errors, acks); never dropped as telemetry is."""
        kind, fields = unpack(message)
        self.deliver(kind, encode(kind, fields))

    async def pump(self) -> None:
        """Sender task: sends what was queued (deliver sends at once what it can); it ends with
        the error of a failed send, its own or deliver's."""
        while True:
            if self._failed is not None:
                raise self._failed
            if self._finishing is not None:  # deliver's send still going: it goes first
                await self.queue.wait()
                continue
            if not self.queue:
                self._idle = True
                try:
                    await self.queue.wait()
                finally:
                    self._idle = False
                continue
            text = await self.queue.get()
            await self.ws.send_text(text)


class Hub:
    def __init__(self, max_telemetry: int = 64, max_total: int = 2048, slow_after_s: float = 3.0) -> None:
        self._clients: set[Client] = set()
        self._max_telemetry = max_telemetry
        self._max_total = max_total
        self._slow_after_s = slow_after_s
        self.published = 0
        # What a new client needs first (current run, state, lease, ROS bridge...): each part's
        # source adds itself with add_snapshot(), in the order the client receives them.
        self._snapshots: list[Callable[[], Iterable[ServerMessage]]] = []
        # Called with every published message (its typed model) before the fan-out (the room's
        # bench publisher: it hears what the dashboards hear).
        self.listeners: list[Callable[[ServerMessage], None]] = []
        # Called after a client connected: producers that slow down with nobody connected
        # (server/runs/reader.py) speed up at once instead of at their next idle wake-up.
        self.on_client: list[Callable[[], None]] = []
        # Per-client filtering (ownership.attach sets both): whose a message is, and whether a
        # client's user may see what that owner owns. The defaults let everyone see everything.
        self.scope: Callable[[str, dict[str, Any]], Scoped | None] = lambda message_type, payload: None
        self.may_see: Callable[[Any, str | None], bool] = lambda user, owner: True

    @property
    def clients(self) -> int:
        return len(self._clients)

    def wants(self, topic: str) -> bool:
        """Whether a message of `topic` would reach anyone now: a client subscribed to it, or a
        listener (listeners hear everything). The producers of the costly periodic streams
        (telemetry, monitor lines, timing) ask first and build nothing nobody receives: with
        no dashboard open they cost next to nothing, and they resume at the next publication
        after a client connects (issue 30: the appliance's idle footprint)."""
        if self.listeners:
            return True
        for client in self._clients:  # a loop, not any(genexpr): asked 2-3 times a reader batch
            if topic in client.topics:
                return True
        return False

    def add_snapshot(self, source: Callable[[], Iterable[ServerMessage]]) -> None:
        """`source()`: the messages a client connecting now receives first; sources are asked in
        the order they were added."""
        self._snapshots.append(source)

    def snapshot(self) -> list[ServerMessage]:
        return [message for source in self._snapshots for message in source()]

    def new_client(self, ws: WebSocket, user: Any = None) -> Client:
        """`user`: who is connecting (set before the snapshot, which is filtered as any message)."""
        client = Client(ws, ClientQueue(self._max_telemetry, self._max_total, self._slow_after_s))
        client.user = user
        for message in self.snapshot():
            kind, fields = unpack(message)
            self._fan_out(kind, fields, (client,), topics=False)
        self._clients.add(client)
        for fn in self.on_client:
            fn()
        return client

    def disconnect_user(self, user_id: int, reason: str) -> int:
        """Close every WebSocket of the user with this id (their sessions ended: disabled, reset);
        how many were open."""
        n = 0
        for client in tuple(self._clients):
            if client.user is not None and client.user.id == user_id:
                client.kick_reason = reason
                client.kicked.set()
                n += 1
        return n

    def remove(self, client: Client) -> None:
        self._clients.discard(client)

    def publish_to_owner(self, message: ServerMessage, owner: str | None) -> None:
        """A message only for `owner` (a username) and whoever may see what they own (educators);
        owner None: educators only. Nobody else receives anything in its place."""
        self._publish(message, Scoped(owner, None))

    def publish_to_educators(self, message: ServerMessage) -> None:
        self._publish(message, Scoped(None, None))

    def publish(self, message: ServerMessage) -> None:
        """Fan a message out to every subscribed client, each getting what `scope` lets them see
        (ownership.scope: the owner's part of a run to its owner and educators, the public part to
        the rest). Never blocks, never raises per client; raises TypeError for anything but a
        server/ws/messages.py server model."""
        self._publish(message, None)

    def publish_fields(self, message_type: str, fields: dict[str, Any]) -> None:
        """`publish` for a message given as its wire fields (JSON values, the fields its sender
        sets), not a model: for the one stream whose model costs more than the rest of its fan-out
        (the reader's telemetry, 5 messages a second: building and dumping the model ~22 us a
        message, issue 30 item 4). Its producer checks that its fields fit the model where they
        could go wrong (its first message, server/runs/reader.py) and builds every later one
        the same way; tests/server/test_ws_schema.py checks what a session receives. Listeners
        (which take models) get one, validated, when there are any."""
        if message_type not in SERVER_KINDS:
            raise TypeError(f"{message_type!r} is not a server message kind (server/ws/messages.py)")
        if self.listeners:
            message = SERVER_KINDS[message_type].model_validate({"type": message_type, **fields})
            self._publish(message, None)  # type: ignore[arg-type]  # SERVER_KINDS holds server models only
            return
        if not self._clients:
            return
        self.published += 1
        self._fan_out(message_type, fields, tuple(self._clients))

    def _publish(self, message: ServerMessage, audience: Scoped | None) -> None:
        if not self.listeners and not self._clients:
            # Nobody to tell: not even dumped (a deadline-miss alarm a second on a busy machine,
            # with no dashboard open: issue 30 item 4); still only a server model is taken.
            if not isinstance(message, SERVER):
                raise TypeError(
                    f"the hub sends server/ws/messages.py models (ServerMessage), not {type(message).__name__}"
                )
            return
        kind, fields = unpack(message)
        for listener in self.listeners:
            try:
                listener(message)
            except Exception:  # a listener's bug must not stop the fan-out
                import logging

                logging.getLogger(__name__).exception("hub listener failed")
        if not self._clients:
            return
        self.published += 1
        self._fan_out(kind, fields, tuple(self._clients), audience=audience)

    def _scope(self, message_type: str, payload: dict[str, Any]) -> Scoped | None:
        try:
            return self.scope(message_type, payload)
        except Exception:
            import logging

            logging.getLogger(__name__).exception("hub scope failed for %s; educators only", message_type)
            return _FAIL_CLOSED

    def _fan_out(
        self,
        message_type: str,
        payload: dict[str, Any],
        clients: Iterable[Client],
        topics: bool = True,
        audience: Scoped | None = None,
    ) -> None:
        """Each client gets the full message or the public one; each is encoded at most once.
        `audience`: given by the publisher (publish_to_owner), else the scope rule decides."""
        scoped = audience if audience is not None else self._scope(message_type, payload)
        text: str | None = None
        public: str | None = None
        for client in clients:
            if topics and message_type not in client.topics:
                continue
            if scoped is None or client.sees(scoped.owner, self.may_see):
                if text is None:
                    text = encode(message_type, payload)
                client.deliver(message_type, text)
            elif scoped.public is not None:
                if public is None:
                    shown = scoped.public() if callable(scoped.public) else scoped.public
                    public = encode(message_type, shown)
                client.deliver(message_type, public)
