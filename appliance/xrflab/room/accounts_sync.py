"""One class list: accounts and roles are managed in the room; every enrolled bench accepts them.

The room publishes its whole accounts table (usernames, roles, names, argon2id hashes, disabled,
must-change) as one retained message on ``xrf/accounts`` whenever it changes (``RoomAccounts``:
its digest is looked at twice a second), with a ``version`` that only grows (payloads.ClassList: at
most ``CLASS_LIST_MAX`` accounts, every field bounded as the accounts themselves are). The broker's ACL lets
benches read it and nobody but the room write it.

A bench (``BenchAccounts``) applies a newer version to its own accounts database: new accounts are
created, changed ones updated; a new password, a disabled account or a changed role ends that
user's sessions, token and WebSockets at once (so a disable in the room takes effect on every
bench within seconds). Accounts the room no longer lists are disabled. Because the accounts are in
the bench's own database, a bench keeps accepting everyone it knows while the room or the broker
is down; the retained list brings it up to date when it reconnects.

Accounts the bench had before it was enrolled (its own ``admin``, for when there is no room) stay
the bench's: a room account of the same name is not applied there (listed as a conflict).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

from .payloads import ClassList

log = logging.getLogger(__name__)


def digest(users: list[dict[str, Any]]) -> str:
    return hashlib.sha256(json.dumps(users, sort_keys=True).encode()).hexdigest()


class RoomAccounts:
    """The room's side: what to publish, and whether it changed."""

    def __init__(self, accounts: Any) -> None:
        self.accounts = accounts
        self.version = 0
        self._digest = ""

    def changed(self) -> ClassList | None:
        """The list to publish when it differs from the last one, else None (ValueError: a list
        the contract cannot carry, e.g. more than CLASS_LIST_MAX accounts)."""
        users = self.accounts.export_hashed()
        d = digest(users)
        if d == self._digest:
            return None
        self._digest = d
        # wall-clock ms: a restarted room still counts above what the benches have
        self.version = max(self.version + 1, time.time_ns() // 1_000_000)
        return ClassList.make(version=self.version, users=users)

    def current(self) -> ClassList:
        self._digest = ""
        out = self.changed()
        assert out is not None
        return out


class BenchAccounts:
    """The bench's side. `state` (<data>/room/accounts.json) remembers the version applied, which
    names the room owns here, and the names that were the bench's own before."""

    def __init__(self, security: Any, folder: Path) -> None:
        self.security = security
        self.path = folder / "accounts.json"
        try:
            self.state = json.loads(self.path.read_text())
        except (OSError, ValueError):
            self.state = {"version": 0, "owned": [], "local": None, "conflicts": []}

    @property
    def version(self) -> int:
        return int(self.state.get("version", 0))

    def apply(self, body: ClassList) -> int:
        """Apply a class list from the room; returns how many accounts' sessions were ended."""
        accounts = self.security.accounts
        version = body.version
        if accounts is None or version <= self.version:
            return 0  # older, or the same again (retained on every reconnect)
        if self.state.get("local") is None:
            # first list: what exists now is the bench's own
            self.state["local"] = [u.username for u in accounts.list()]
        local = set(self.state["local"])
        owned: set[str] = set(self.state.get("owned", []))
        listed: set[str] = set()
        conflicts, ended = [], 0
        for u in body.users:
            name = u.username
            if name in local:
                conflicts.append(name)
                continue
            try:
                user, revoked = accounts.put_hashed(
                    name, u.role, u.password_hash, u.full_name, u.email, u.disabled, u.must_change
                )
            except Exception as exc:
                log.warning("room class list: %s: %s", name, exc)
                continue
            listed.add(user.username)
            if revoked:
                ended += 1
                self._ended(user)
        for name in owned - listed:  # removed from the class list: no longer welcome here
            user = accounts.by_name(name)
            if user is not None and not user.disabled:
                accounts.update(user.id, disabled=True)
                ended += 1
                self._ended(user)
        self.state.update(version=version, owned=sorted(owned | listed), conflicts=sorted(conflicts))
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.state))
        tmp.replace(self.path)
        return ended

    def _ended(self, user: Any) -> None:
        self.security.disconnect(user.id)  # its open dashboards close now
        lease = self.security.lease
        if lease is not None:
            lease.forget(user.id, "account changed in the room")
