"""The bench lease: one holder drives the bench (commands, setpoints, starting and ending runs);
everyone else watches.

- Free lease: any student or educator takes it. Held: others queue; when the holder releases it
  (or is released), the first in the queue becomes the holder at once.
- Released when the holder releases it, after `idle_s` without a drive action by the holder, or
  when an educator takes it over. NOT when a run ends or crashes: a student in a practical runs,
  edits and runs again, and losing the bench at every run end (and having to take it again, or
  finding someone else took it) was the most frequent interruption (issue 19).
- An educator takes it over at any time; the previous holder is told (the `lease` message names
  them in `previous` with event `takeover`). A student taken over from is put at the head of the
  queue (the message's `reason` says so): the bench comes back to them when the educator
  releases it, instead of to whoever queued behind them.
- Stopping is always safe (the STOP rule): anyone but an observer may pause or stop a running
  controller. When someone who does not hold the bench does, the holder is told who (event
  `intervention`, `by` that user, `command` pause or stop).
- Educators drive without holding it (they can take it over anyway; see docs/developers/security.md).

Every change is published as a `lease` WebSocket message and recorded in the audit trail.
In memory: an appliance restart frees the bench (the run ends with it anyway).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ...errors import XrfError
from ..runs.lifecycle import RunObserver
from ..ws.messages import LeaseMessage
from .accounts import User

if TYPE_CHECKING:
    from ..runs.run import Run
    from ..runs.store import RunRow


class LeaseError(XrfError):
    """A lease action refused (409 by default, 403 releasing someone else's): an XrfError, so
    the routes let server/http/errors.py answer it."""

    status = 409


@dataclass
class Holder:
    user: User
    since: float
    last_active: float  # monotonic
    run_id: int | None = None  # the run the holder started, if any (its end keeps the lease)


def _who(user: User | None) -> dict[str, Any] | None:
    return None if user is None else {"id": user.id, "username": user.username, "role": user.role}


class Lease(RunObserver):
    """Also a run observer (server/runs/lifecycle.py), after host logging: a run's end is the holder's activity."""

    name = "bench lease"

    def __init__(
        self,
        idle_s: float,
        publish: Callable[[LeaseMessage], None],
        record: Callable[[User | None, str, dict[str, Any]], None],
    ) -> None:
        self.idle_s = idle_s
        self._publish = publish
        self._record = record
        # Set when someone takes the bench: watch_idle waits for it (made by start(), in the
        # event loop the watch runs in; an app started twice, as tests do, gets a new one).
        self._held: asyncio.Event | None = None
        self._holder: Holder | None = None
        self.queue: list[User] = []
        self._task: asyncio.Task[None] | None = None
        self.looks = 0  # watch_idle's looks (tests: it sleeps while nobody holds the bench)

    @property
    def holder(self) -> Holder | None:
        return self._holder

    @holder.setter
    def holder(self, h: Holder | None) -> None:
        self._holder = h
        if h is not None and self._held is not None:
            self._held.set()

    # -- queries ----------------------------------------------------------------------------------

    def holds(self, user: User) -> bool:
        return self.holder is not None and self.holder.user.id == user.id

    def payload(self, event: str = "current", **extra: Any) -> dict[str, Any]:
        h = self.holder
        idle_left = None
        if h is not None:
            idle_left = max(0.0, self.idle_s - (time.monotonic() - h.last_active))
        return {
            "event": event,
            "holder": None if h is None else {**_who(h.user), "since": h.since},  # type: ignore[dict-item]
            "queue": [_who(u) for u in self.queue],
            "idle_s": self.idle_s,
            "idle_left_s": idle_left,
            **extra,
        }

    def message(self, event: str = "current", **extra: Any) -> LeaseMessage:
        """The `lease` WebSocket message: `payload`, checked against messages.LeaseMessage."""
        return LeaseMessage.model_validate(self.payload(event, **extra))

    # -- changes ----------------------------------------------------------------------------------

    def touch(self, user: User) -> None:
        """A drive action by `user`: the holder's inactivity timer restarts."""
        if self.holds(user):
            assert self.holder is not None
            self.holder.last_active = time.monotonic()

    def take(self, user: User) -> dict[str, Any]:
        if self.holds(user):
            self.touch(user)
            return self.payload()
        if self.holder is None:
            self._grant(user, "take", user)
            return self.payload()
        if not user.is_educator:
            raise LeaseError(f"the bench is held by {self.holder.user.username}; queue for it")
        previous = self.holder.user
        self._drop_from_queue(user)
        self.holder = Holder(user, time.time(), time.monotonic())
        if previous.is_educator:  # educators do not queue (they take over whenever they need to)
            self._changed("takeover", user, previous=_who(previous))
        else:
            # First in the queue: the educator's release hands the bench straight back.
            self._drop_from_queue(previous)
            self.queue.insert(0, previous)
            self._changed(
                "takeover",
                user,
                previous=_who(previous),
                reason=f"{previous.username} is first in the queue and gets the bench back when {user.username} releases it",
            )
        return self.payload()

    def release(self, user: User, reason: str = "release") -> dict[str, Any]:
        if self.holder is None:
            raise LeaseError("nobody holds the bench")
        if not self.holds(user) and not user.is_educator:
            raise LeaseError(f"the bench is held by {self.holder.user.username}, not you", 403)
        self._free(reason, user)
        return self.payload()

    def enqueue(self, user: User) -> dict[str, Any]:
        if self.holds(user):
            raise LeaseError("you hold the bench already")
        if self.holder is None:
            return self.take(user)
        if all(u.id != user.id for u in self.queue):
            self.queue.append(user)
            self._changed("queue", user)
        return self.payload()

    def leave_queue(self, user: User) -> dict[str, Any]:
        if self._drop_from_queue(user):
            self._changed("unqueue", user)
        return self.payload()

    def forget(self, user_id: int, reason: str) -> None:
        """An account was disabled or changed role: it neither holds nor waits any more."""
        if any(u.id == user_id for u in self.queue):
            self.queue = [u for u in self.queue if u.id != user_id]
            self._changed("unqueue", None, reason=reason)
        if self.holder is not None and self.holder.user.id == user_id:
            self._free(reason, None)

    def intervened(self, user: User, command: str) -> None:
        """`user` paused or stopped the controller (the STOP rule lets anyone but an observer):
        when the bench is someone else's, its holder is told who did it. Not a change of the
        lease: published, not audited here (the command itself is audited by the route)."""
        h = self.holder
        if h is None or h.user.id == user.id:
            return
        self._publish(LeaseMessage.model_validate(self.payload("intervention", by=_who(user), command=command)))

    def started_run(self, user: User, run_id: int) -> None:
        if self.holds(user):
            assert self.holder is not None
            self.holder.run_id = run_id

    def run_ended(self, run_id: int | None, owner: str | None = None) -> None:
        """A run ended (stopped, quit, crashed): the holder keeps the bench for the next run (see
        the module docstring). The end counts as activity, so the idle time starts again from
        here: a holder watching a long run was not idle, and gets the full time to react."""
        h = self.holder
        if h is None or run_id is None:
            return
        if h.run_id == run_id or (owner and owner == h.user.username):
            h.run_id = None
            h.last_active = time.monotonic()

    async def on_ended(self, row: RunRow, run: Run | None) -> None:
        self.run_ended(row.id, row.owner or None)

    def check_idle(self) -> None:
        h = self.holder
        if h is not None and time.monotonic() - h.last_active >= self.idle_s:
            self._free("idle", None)

    async def watch_idle(self) -> None:
        """Frees an idle holder at its idle time: sleeps until the holder's deadline (a drive
        action or a new holder meanwhile only moves it later: looked at again then), and while
        nobody holds the bench until someone takes it. It looked once a second (issue 30 item 4,
        session 14: a wake-up of the idle event loop's for a deadline minutes away, or for
        nobody)."""
        held = self._held = asyncio.Event()
        while True:
            self.looks += 1
            h = self.holder
            if h is None:
                held.clear()
                await held.wait()
                continue
            left = h.last_active + self.idle_s - time.monotonic()
            if left > 0:
                await asyncio.sleep(left)
            else:
                self.check_idle()

    def start(self) -> None:
        self._task = asyncio.create_task(self.watch_idle(), name="lease-idle")

    def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()

    # -- internals --------------------------------------------------------------------------------

    def _drop_from_queue(self, user: User) -> bool:
        before = len(self.queue)
        self.queue = [u for u in self.queue if u.id != user.id]
        return len(self.queue) != before

    def _grant(self, user: User, event: str, actor: User | None, **extra: Any) -> None:
        self._drop_from_queue(user)
        self.holder = Holder(user, time.time(), time.monotonic())
        self._changed(event, actor, **extra)

    def _free(self, reason: str, actor: User | None) -> None:
        previous = self.holder.user if self.holder else None
        self.holder = None
        if self.queue:
            nxt = self.queue.pop(0)
            self._grant(nxt, "handover", actor, previous=_who(previous), reason=reason)
        else:
            self._changed("released", actor, previous=_who(previous), reason=reason)

    def _changed(self, event: str, actor: User | None, **extra: Any) -> None:
        """Publish and audit a change; `by` in the message is who did it (None: the appliance)."""
        extra.pop("holder_user", None)
        payload = self.payload(event, by=_who(actor), **extra)
        self._publish(LeaseMessage.model_validate(payload))
        self._record(actor, f"lease.{event}", {k: v for k, v in payload.items() if k not in ("idle_s", "idle_left_s")})
