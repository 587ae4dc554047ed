"""The hub's public API (no module reads its client set or patches its snapshot): snapshot
sources in order, per-audience publishing with the ownership rule, closing one user's sockets;
it takes server/ws/messages.py models only and sends the fields their senders set."""

from __future__ import annotations

import asyncio
import json

import pytest

from xrflab.server.security import ownership
from xrflab.server.security.accounts import User
from xrflab.server.ws.hub import Client, Hub
from xrflab.server.ws.messages import AlarmMessage, BuildMessage, ErrorMessage, LeaseMessage, RunMessage, StateMessage

ALICE = User(1, "alice", "student")
BOB = User(2, "bob", "student")
TEACH = User(3, "teach", "educator")


def _queued(client: Client) -> list[dict[str, object]]:
    """Everything queued for the client, in the order its socket would send it."""
    q = client.queue

    async def drain() -> list[str]:
        return [await q.get() for _ in range(len(q))]

    return [json.loads(t) for t in asyncio.run(drain())]


def _hub() -> tuple[Hub, dict[str, Client]]:
    hub = Hub()
    hub.may_see = ownership.may_see
    hub.add_snapshot(lambda: [RunMessage(event="current", run=None, active=False)])
    hub.add_snapshot(lambda: [LeaseMessage(event="current", holder=None, queue=[], idle_s=600, idle_left_s=None)])
    clients = {u.username: hub.new_client(None, u) for u in (ALICE, BOB, TEACH)}  # type: ignore[arg-type]
    return hub, clients


def test_snapshot_sources_in_the_order_added() -> None:
    _, clients = _hub()
    for c in clients.values():
        assert [m["type"] for m in _queued(c)] == ["run", "lease"]  # a new client gets them first


def test_publish_to_owner_and_to_educators() -> None:
    hub, clients = _hub()
    for c in clients.values():
        _queued(c)  # the snapshot
    hub.publish_to_owner(BuildMessage(build="p", line="alice's compiler output"), "alice")
    hub.publish_to_educators(AlarmMessage(kind="disk", message="for educators"))
    hub.publish(AlarmMessage(kind="room", message="for everyone"))
    got = {name: [m.get("line") or m.get("message") for m in _queued(c)] for name, c in clients.items()}
    assert got == {
        "alice": ["alice's compiler output", "for everyone"],
        "bob": ["for everyone"],
        "teach": ["alice's compiler output", "for educators", "for everyone"],
    }


def test_disconnect_user_closes_only_that_users_sockets() -> None:
    hub, clients = _hub()
    assert hub.disconnect_user(BOB.id, "your session ended") == 1
    assert clients["bob"].kicked.is_set() and clients["bob"].kick_reason == "your session ended"
    assert not clients["alice"].kicked.is_set() and not clients["teach"].kicked.is_set()


def _texts(client: Client) -> list[str]:
    q = client.queue

    async def drain() -> list[str]:
        return [await q.get() for _ in range(len(q))]

    return asyncio.run(drain())


def test_the_hub_refuses_anything_but_a_message_model() -> None:
    hub, clients = _hub()
    for c in clients.values():
        _queued(c)  # the snapshot
    heard: list[str] = []
    hub.listeners.append(lambda message: heard.append(message.type))
    plain = {"type": "alarm", "kind": "room", "message": "a dict"}
    with pytest.raises(TypeError, match="server/ws/messages.py models"):
        hub.publish(plain)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="server/ws/messages.py models"):
        hub.publish_to_owner(plain, "alice")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="server/ws/messages.py models"):
        hub.publish_to_educators(plain)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="server/ws/messages.py models"):
        clients["alice"].reply(plain)  # type: ignore[arg-type]
    hub.add_snapshot(lambda: [plain])  # type: ignore[list-item]
    with pytest.raises(TypeError, match="server/ws/messages.py models"):
        hub.new_client(None, ALICE)  # type: ignore[arg-type]
    assert heard == [] and all(_queued(c) == [] for c in clients.values())  # nothing went anywhere


def test_a_message_carries_the_fields_its_sender_set() -> None:
    """What app.js and the room's publisher read: a field left out is absent, one set to None is
    null, `from_` is `from`, and `type` comes first, as the dicts the senders built before."""
    hub, clients = _hub()
    alice = clients["alice"]
    _queued(alice)
    hub.publish(
        StateMessage(run_id=None, active=False, state=0, name="NO RUN", allowed=[], rejected=None, last_error=0)
    )
    hub.publish(AlarmMessage.model_validate({"kind": "room", "message": "m", "from": "teach"}))
    alice.reply(ErrorMessage(error="malformed JSON"))
    assert _texts(alice) == [
        '{"type":"state","run_id":null,"active":false,"state":0,"name":"NO RUN","allowed":[],"rejected":null,'
        '"last_error":0}',
        '{"type":"alarm","kind":"room","message":"m","from":"teach"}',
        '{"type":"error","error":"malformed JSON"}',
    ]


def _telemetry_fields(run_id: int = 7) -> dict[str, object]:
    """A telemetry message's wire fields as the reader builds them: two samples, oldest first."""
    samples = [
        {
            "cycle": cycle,
            "t_ns": cycle * 5,
            "t": cycle * 0.5,
            "state": 4,
            "enc": [1, 2],
            "din": [0, 1, 0, 0],
            "pwm": [10, -10],
            "dout": [0, 1],
            "xeno2ros": {"u": 1.5},
            "ros2xeno_t_sent_ns": 0,
        }
        for cycle in (3, 4)
    ]
    return {"run_id": run_id, "samples": samples, "ros2xeno": {"r": 2.0}, "lost": 0}


def test_telemetry_by_its_fields_goes_out_as_its_model_would() -> None:
    """Hub.publish_fields (the reader's telemetry, no model per message): the same text and the
    same per-audience rule as the model through publish; a listener still gets a model, checked;
    a kind the protocol does not have is refused."""
    from xrflab.server.ws.messages import TelemetryMessage

    hub, clients = _hub()
    hub.scope = lambda kind, payload: ownership.scope(kind, payload, lambda run_id: "alice")
    for c in clients.values():
        _queued(c)  # the snapshot
    fields = _telemetry_fields()
    hub.publish(TelemetryMessage(**fields))  # type: ignore[arg-type]
    by_model = {name: _texts(c) for name, c in clients.items()}
    hub.publish_fields("telemetry", fields)
    by_fields = {name: _texts(c) for name, c in clients.items()}
    assert by_fields == by_model
    owners = json.loads(by_fields["alice"][0])
    assert [x["xeno2ros"] for x in owners["samples"]] == [{"u": 1.5}] * 2  # the owner's part to its owner
    assert owners["ros2xeno"] == {"r": 2.0}
    public = json.loads(by_fields["bob"][0])
    assert [x["xeno2ros"] for x in public["samples"]] == [{}, {}] and public["ros2xeno"] == {}  # the rest
    assert [x["cycle"] for x in public["samples"]] == [3, 4] and public["samples"][0]["enc"] == [1, 2]

    heard: list[object] = []
    hub.listeners.append(heard.append)
    hub.publish_fields("telemetry", fields)
    assert [type(m) for m in heard] == [TelemetryMessage]
    with pytest.raises(ValueError):  # pydantic's ValidationError: checked where listeners hear it
        hub.publish_fields("telemetry", {**fields, "samples": [{"enc": "not a list"}]})
    with pytest.raises(TypeError, match="not a server message kind"):
        hub.publish_fields("no-such-kind", fields)


def test_the_public_copy_is_made_only_for_a_client_that_needs_it() -> None:
    """ownership.scope's public part of telemetry is a function (5 messages a second): with only
    the owner and an educator connected it is never called; with someone else, once a message
    however many of them there are."""
    made: list[int] = []

    def scope(kind: str, payload: dict[str, object]) -> object:
        scoped = ownership.scope(kind, payload, lambda run_id: "alice")
        assert scoped is not None and callable(scoped.public)
        public = scoped.public

        def counted() -> dict[str, object]:
            made.append(1)
            return public()

        return scoped._replace(public=counted)

    hub = Hub()
    hub.may_see = ownership.may_see
    hub.scope = scope  # type: ignore[assignment]
    owner_and_educator = [hub.new_client(None, u) for u in (ALICE, TEACH)]  # type: ignore[arg-type]
    hub.publish_fields("telemetry", _telemetry_fields())
    assert made == [] and all(len(_texts(c)) == 1 for c in owner_and_educator)
    others = [hub.new_client(None, u) for u in (BOB, User(4, "carol", "observer"))]  # type: ignore[arg-type]
    hub.publish_fields("telemetry", _telemetry_fields())
    assert made == [1]
    assert [[x["xeno2ros"] for x in json.loads(_texts(c)[0])["samples"]] for c in others] == [[{}, {}], [{}, {}]]


class _Socket:
    """What a client's messages are sent through (starlette's WebSocket.send_text), recording
    them; while `hold` is set a send waits, as one to a transport that asked to pause writing."""

    def __init__(self) -> None:
        self.sent: list[str] = []
        self.hold: asyncio.Event | None = None
        self.gone = False

    async def send_text(self, text: str) -> None:
        if self.hold is not None:
            await self.hold.wait()
        if self.gone:
            raise ConnectionResetError("the browser went away")
        self.sent.append(json.loads(text)["message"])


def test_a_message_goes_out_in_the_publishers_turn_and_in_order_when_a_send_waits() -> None:
    """With the client's pump idle a message is sent by the publisher itself (no wake-up of the
    pump per message); one that has to wait is finished on its own and what comes meanwhile is
    queued behind it; a failed send ends the pump with its error."""

    async def main() -> None:
        hub = Hub()
        sock = _Socket()
        client = hub.new_client(sock, TEACH)  # type: ignore[arg-type]
        pump = asyncio.create_task(client.pump())
        await asyncio.sleep(0)  # the pump is waiting
        hub.publish(AlarmMessage(kind="room", message="1"))
        assert sock.sent == ["1"]  # already sent: nobody else ran
        sock.hold = asyncio.Event()
        hub.publish(AlarmMessage(kind="room", message="2"))  # waits in the send
        hub.publish(AlarmMessage(kind="room", message="3"))  # queued behind it
        await asyncio.sleep(0)  # one turn of the event loop: the held send is waiting, nothing more
        assert sock.sent == ["1"] and len(client.queue) == 1
        sock.hold.set()
        for _ in range(10):
            await asyncio.sleep(0)
        assert sock.sent == ["1", "2", "3"] and len(client.queue) == 0
        sock.hold = None
        hub.publish(AlarmMessage(kind="room", message="4"))
        assert sock.sent == ["1", "2", "3", "4"]
        sock.gone = True
        hub.publish(AlarmMessage(kind="room", message="5"))
        with pytest.raises(ConnectionResetError):
            await asyncio.wait_for(pump, 5)
        client.stop()

    asyncio.run(main())


def test_monitor_lines_by_their_fields_go_out_as_their_model_would() -> None:
    """The reader's monitor message (reader.monitor_message_fields through Hub.publish_fields):
    the same text as MonitorMessage through publish, to the owner and educators only."""
    from xrflab.channels.rings import MonitorLine as RingLine
    from xrflab.server.runs.reader import monitor_message_fields
    from xrflab.server.ws.messages import MonitorLine, MonitorMessage

    hub, clients = _hub()
    hub.scope = lambda kind, payload: ownership.scope(kind, payload, lambda run_id: "alice")
    for c in clients.values():
        _queued(c)  # the snapshot
    lines = [RingLine(cycle=12, t_ns=345, text="x = 1.5"), RingLine(cycle=13, t_ns=346, text='"quoted" \\u00e9')]
    hub.publish(
        MonitorMessage(
            run_id=7,
            source="monitor",
            lines=[MonitorLine(cycle=m.cycle, t_ns=m.t_ns, text=m.text) for m in lines],
            lost=2,
        )
    )
    by_model = {name: _texts(c) for name, c in clients.items()}
    fields = monitor_message_fields(7, lines, 2)
    MonitorMessage.model_validate(fields)
    hub.publish_fields("monitor", fields)
    assert {name: _texts(c) for name, c in clients.items()} == by_model
    assert [len(by_model[n]) for n in ("alice", "bob", "teach")] == [1, 0, 1]


def test_the_timing_message_by_its_fields_goes_out_as_its_model_would() -> None:
    """The timing task's message (timing.timing_message_fields through Hub.publish_fields, once a
    second while someone takes `timing`): the same text as TimingMessage through publish, to the
    same clients, from a status and histograms as the loop leaves them."""
    from xrflab.channels import ffi, lib
    from xrflab.channels.status import histogram_from_struct, status_from_struct
    from xrflab.server.runs.timing import timing_message_fields
    from xrflab.server.ws.messages import Histogram, StageSummary, TimingMessage

    hub, clients = _hub()
    hub.scope = lambda kind, payload: ownership.scope(kind, payload, lambda run_id: "alice")
    for c in clients.values():
        _queued(c)  # the snapshot
    raw = ffi.new("struct xrf_status *")
    raw.cycles, raw.missed, raw.log_lost, raw.host_lost = 12_345, 3, 1, 2
    for i, ns in enumerate((900, 15_000, 70, 0, 2_000_000, 450, 10, 0)):
        h = raw.hist[i]
        for k in range(5 if ns else 0):
            v = ns + 37 * k
            h.buckets[lib.xrf_hist_bucket(v)] += 1
            h.count += 1
            h.sum_ns += v
            h.min_ns = v if k == 0 else min(h.min_ns, v)
            h.max_ns = max(h.max_ns, v)
    s = status_from_struct(raw)
    from xrflab.channels import STAGE_NAMES

    hists = {name: histogram_from_struct(raw.hist[i]) for i, name in enumerate(STAGE_NAMES)}
    wake = hists["wakeup"]
    hub.publish(
        TimingMessage(
            run_id=7,
            cycles=s.cycles,
            misses=s.missed,
            cycle_freq=1000,
            stages={
                name: StageSummary(
                    count=h.count, min=h.min, max=h.max, mean=h.mean, p50=h.percentile(50), p99=h.percentile(99)
                )
                for name, h in hists.items()
            },
            jitter=Histogram(edges=wake.edges, counts=wake.counts),
            histograms={name: Histogram(edges=h.edges, counts=h.counts) for name, h in hists.items()},
            telemetry_sent=99,
            log_lost=s.log_lost,
            host_lost=s.host_lost,
        )
    )
    by_model = {name: _texts(c) for name, c in clients.items()}
    fields = timing_message_fields(7, s, hists, 1000, 99)
    TimingMessage.model_validate(fields)
    hub.publish_fields("timing", fields)
    assert {name: _texts(c) for name, c in clients.items()} == by_model
    assert all(len(t) == 1 for t in by_model.values()) and '"p99":' in by_model["alice"][0]
