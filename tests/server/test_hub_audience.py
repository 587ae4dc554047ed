"""The hub's public API (no module reads its client set or patches its snapshot): snapshot
sources in order, per-audience publishing with the ownership rule, closing one user's sockets."""

from __future__ import annotations

import asyncio
import json

from xrflab.server import ownership
from xrflab.server.accounts import User
from xrflab.server.hub import Client, Hub

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
    hub.add_snapshot(lambda: [("run", {"event": "current", "run": None})])
    hub.add_snapshot(lambda: [("lease", {"event": "current", "holder": None})])
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
    hub.publish_to_owner("build", {"build": "p", "line": "alice's compiler output"}, "alice")
    hub.publish_to_educators("alarm", {"kind": "disk", "message": "for educators"})
    hub.publish("alarm", {"kind": "room", "message": "for everyone"})
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
