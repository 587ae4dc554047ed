"""The bench lease's rules in-process (server/security/lease.py): take, queue, hand over, educator
takeover, idle release, a run's end as activity. No appliance: the Lease is given a list for its
WebSocket messages and one for its audit records (test_lease.py drives the same through a server)."""

from __future__ import annotations

import time
from typing import Any

import pytest

from xrflab.server.security.accounts import User
from xrflab.server.security.lease import Lease
from xrflab.server.ws.messages import LeaseMessage

ANN = User(1, "ann", "student")
BOB = User(2, "bob", "student")
CAT = User(3, "cat", "student")
EVE = User(4, "eve", "educator")


class Bench:
    def __init__(self, idle_s: float = 60.0) -> None:
        self.messages: list[LeaseMessage] = []
        self.audit: list[tuple[str | None, str, dict[str, Any]]] = []
        self.lease = Lease(idle_s, self.messages.append, self._record)

    def _record(self, actor: User | None, action: str, detail: dict[str, Any]) -> None:
        self.audit.append((actor.username if actor else None, action, detail))

    def events(self) -> list[str]:
        return [m.event for m in self.messages]

    def holder(self) -> str | None:
        h = self.lease.holder
        return None if h is None else h.user.username


def _refused(call: Any, *args: Any) -> int:
    with pytest.raises(Exception) as err:  # LeaseError today, an XrfError kind tomorrow: both carry .status
        call(*args)
    return int(err.value.status)  # type: ignore[attr-defined]


def test_take_queue_and_handover_in_order() -> None:
    b = Bench()
    b.lease.take(ANN)
    assert b.holder() == "ann" and b.lease.holds(ANN)
    assert _refused(b.lease.take, BOB) == 409  # a student cannot take a held bench
    b.lease.enqueue(BOB)
    b.lease.enqueue(CAT)
    b.lease.enqueue(BOB)  # queueing twice keeps one place
    assert [u.username for u in b.lease.queue] == ["bob", "cat"]
    assert _refused(b.lease.enqueue, ANN) == 409  # the holder does not queue
    assert _refused(b.lease.release, BOB) == 403  # nor releases someone else's lease

    b.lease.release(ANN)
    assert b.holder() == "bob" and [u.username for u in b.lease.queue] == ["cat"]
    handover = b.messages[-1]
    assert handover.event == "handover" and handover.previous is not None
    assert handover.previous.username == "ann" and handover.reason == "release"
    assert b.events() == ["take", "queue", "queue", "handover"]

    b.lease.leave_queue(CAT)
    b.lease.release(BOB)
    assert b.holder() is None and b.events()[-2:] == ["unqueue", "released"]
    assert _refused(b.lease.release, BOB) == 409  # nobody holds it


def test_enqueue_on_a_free_bench_takes_it_and_taking_again_is_a_touch() -> None:
    b = Bench()
    b.lease.enqueue(ANN)
    assert b.holder() == "ann" and b.events() == ["take"]
    b.lease.take(ANN)
    assert b.events() == ["take"]  # nothing changed, nothing published


def test_an_educator_takes_over_and_the_previous_holder_is_named() -> None:
    b = Bench()
    b.lease.take(ANN)
    b.lease.enqueue(EVE)
    b.lease.take(EVE)
    # eve is out of the queue once holding; ann, taken over from, is first in it (issue 31)
    assert b.holder() == "eve" and [u.username for u in b.lease.queue] == ["ann"]
    msg = b.messages[-1]
    assert msg.event == "takeover" and msg.previous is not None and msg.previous.username == "ann"
    assert msg.by is not None and msg.by.username == "eve"
    # an educator may release anyone's lease; the bench goes back to ann
    b.lease.take(EVE)
    b.lease.release(EVE)
    assert b.holder() == "ann"


def test_idle_holder_is_released_and_the_queue_moves_on() -> None:
    b = Bench(idle_s=0.05)
    b.lease.take(ANN)
    b.lease.enqueue(BOB)
    b.lease.check_idle()
    assert b.holder() == "ann"  # not idle yet
    b.lease.holder.last_active = time.monotonic() - 1.0  # type: ignore[union-attr]  # an hour of silence, compressed
    b.lease.check_idle()
    assert b.holder() == "bob"
    assert b.messages[-1].event == "handover" and b.messages[-1].reason == "idle"
    assert b.messages[-1].by is None  # the appliance did it
    assert b.audit[-1][0] is None and b.audit[-1][1] == "lease.handover"


def test_a_run_end_keeps_the_lease_and_counts_as_activity() -> None:
    b = Bench(idle_s=10.0)
    b.lease.take(ANN)
    b.lease.started_run(ANN, 7)
    b.lease.holder.last_active = time.monotonic() - 9.0  # type: ignore[union-attr]
    b.lease.run_ended(8)  # someone else's run: nothing
    assert b.lease.holder.run_id == 7  # type: ignore[union-attr]
    b.lease.run_ended(7)
    h = b.lease.holder
    assert h is not None and h.user is ANN and h.run_id is None
    assert time.monotonic() - h.last_active < 1.0  # the idle time starts again at the run's end
    b.lease.check_idle()
    assert b.holder() == "ann"
    # a run ended that the holder owns by name (started before the lease was taken)
    b.lease.holder.last_active = 0.0  # type: ignore[union-attr]
    b.lease.run_ended(9, owner="ann")
    assert time.monotonic() - b.lease.holder.last_active < 1.0  # type: ignore[union-attr]


def test_forget_drops_a_disabled_account_from_queue_and_holder() -> None:
    b = Bench()
    b.lease.take(ANN)
    b.lease.enqueue(BOB)
    b.lease.enqueue(CAT)
    b.lease.forget(BOB.id, "disabled")
    assert [u.username for u in b.lease.queue] == ["cat"]
    b.lease.forget(ANN.id, "role changed")
    assert b.holder() == "cat" and b.messages[-1].reason == "role changed"


def test_payload_counts_down_the_idle_time() -> None:
    b = Bench(idle_s=30.0)
    assert b.lease.payload()["holder"] is None and b.lease.payload()["idle_left_s"] is None
    b.lease.take(ANN)
    b.lease.holder.last_active -= 10.0  # type: ignore[union-attr]
    left = b.lease.payload()["idle_left_s"]
    assert 19.0 < left <= 20.0
    # the audit record leaves the timer out (it says what changed, not when it will expire)
    assert all("idle_left_s" not in detail for _, _, detail in b.audit)


def test_the_idle_watch_sleeps_until_the_holders_time() -> None:
    """The idle watch (`watch_idle`) frees an idle holder at its time, and does not look on a
    timer meanwhile: with nobody holding the bench it waits for a holder, with one it sleeps
    until the holder's deadline (a drive action moves it later). It looked once a second (issue
    30 item 4, session 14: a wake-up of the idle appliance's for nobody)."""
    import asyncio

    async def main() -> None:
        b = Bench(idle_s=0.6)
        b.lease.start()
        try:
            await asyncio.sleep(1.0)  # the point: time with nobody holding the bench
            assert b.lease.looks <= 1, f"{b.lease.looks} looks with nobody holding the bench"
            b.lease.take(ANN)
            await asyncio.sleep(0.4)  # on purpose: idle time of the holder (below idle_s)
            b.lease.touch(ANN)  # a drive action: its idle time starts again
            await asyncio.sleep(0.4)  # on purpose: idle time again, over idle_s since the take, not since the touch
            assert b.holder() == "ann"  # 0.8 s after the take, 0.4 s after its last action
            for _ in range(100):
                if b.holder() is None:
                    break
                await asyncio.sleep(0.05)  # polling: the release at the holder's idle time
            assert b.holder() is None and b.messages[-1].reason == "idle"
            # a look when taken, one at the first deadline, one at the touched one, one after freeing
            assert b.lease.looks <= 5, f"{b.lease.looks} looks for one holder's idle time"
        finally:
            b.lease.stop()

    asyncio.run(main())
