"""Roles and what each may do: the one definition.

Everything else reads these: accounts.py checks a role against ``ROLES``, auth.py's ``may()`` and
``check()`` against ``ROLE_PERMS``, the HTTP models type a role as ``Role``, the room's account
payloads too, and the browser gets the user's permissions (``GET /api/me``: ``perms``) and the list
of roles (``GET /api/roles``): no page compares role names, it asks for a permission.
``tests/lint/test_one_definition.py`` fails on a second list of role names.
"""

from __future__ import annotations

import re
from enum import Enum
from typing import Literal, get_args


class Perm(str, Enum):
    PUBLIC = "public"  # reachable without a login: the login page, health
    SELF = "self"  # any logged-in user, even one who must still change the password: me, logout
    WATCH = "watch"  # observer and up: state, telemetry, runs list, own logs
    STOP = "stop"  # student and up, without the lease: stop/pause whatever runs (safety)
    LEASE = "lease"  # student and up: take, queue for and release the bench lease
    DRIVE = "drive"  # commands, setpoints, starting/ending runs: the lease holder (educators always)
    PROJECTS = "projects"  # student and up: own projects, uploads, builds, own runs' logs
    EDUCATOR = "educator"  # users, self-check, bench profiles, audit, take-over, any project


Role = Literal["educator", "student", "observer"]
ROLES: tuple[Role, ...] = get_args(Role)
# Who an account is: lowercase, 2-32 characters; also a broker-side and file-name-safe token
# (the room's class list carries it: room/payloads.py).
USERNAME_RE = re.compile(r"^[a-z0-9][a-z0-9._-]{1,31}$")
# The role the Users page offers first for a new account.
DEFAULT_ROLE: Role = "student"

ROLE_PERMS: dict[Role, frozenset[Perm]] = {
    "observer": frozenset({Perm.PUBLIC, Perm.SELF, Perm.WATCH}),
    "student": frozenset({Perm.PUBLIC, Perm.SELF, Perm.WATCH, Perm.STOP, Perm.LEASE, Perm.DRIVE, Perm.PROJECTS}),
    "educator": frozenset(Perm),
}
if set(ROLE_PERMS) != set(ROLES):
    raise RuntimeError(f"roles.ROLE_PERMS {sorted(ROLE_PERMS)} and ROLES {sorted(ROLES)} differ")


def role_has(role: str, perm: Perm) -> bool:
    """`role` grants `perm` (before the lease: DRIVE also needs it, but for EDUCATOR roles)."""
    return perm in ROLE_PERMS.get(role, frozenset())  # type: ignore[call-overload]
