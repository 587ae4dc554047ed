"""Permissions: every HTTP route and every WebSocket message type declares the one it needs.

Routes declare theirs with ``dependencies=[requires(Perm.X)]``; a test walks the route table and
fails for any route without one. Accounts, sessions and the bench lease (issue 7) plug into
``check()``; until they land, every request is treated as the built-in local educator, which is
what the appliance was before accounts existed.
"""

from __future__ import annotations

from enum import Enum

from fastapi import Depends, Request


class Perm(str, Enum):
    PUBLIC = "public"        # reachable without a login: the login page, health
    WATCH = "watch"          # observer and up: state, telemetry, runs list, own logs
    DRIVE = "drive"          # commands, setpoints, starting/ending runs: the lease holder
    PROJECTS = "projects"    # student and up: own projects, uploads, builds, own runs' logs
    EDUCATOR = "educator"    # users, self-check, bench profiles, audit, take-over, any project


def check(request: Request, perm: Perm) -> None:
    """Raise an HTTPException when the request may not do `perm`. Replaced by issue 7's accounts."""
    return None


def requires(perm: Perm) -> Depends:
    async def dependency(request: Request) -> None:
        check(request, perm)

    dependency.xrf_permission = perm  # read by the route-table test
    return Depends(dependency)
