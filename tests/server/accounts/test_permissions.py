"""The permission matrix, role x endpoint, for every HTTP route of the app (read from the route
table, so new features' routes are covered the day they land): a role without the route's
permission is refused (401 without a login, 403 with one) and a role with it gets past the
check. Requests carry harmless bodies and made-up ids, so nothing is changed.

Explicit cases with real effects (the lease, ownership, CSRF...) are in test_security.py and
test_lease.py."""

from __future__ import annotations

import re
from typing import Any

import httpx
import pytest
from fastapi.routing import APIRoute
from test_route_table import permissions_of, walk

from xrflab.server.app import create_app
from xrflab.server.security.auth import ROLE_PERMS, Perm
from xrflab.server.settings import Settings

ROLES = ("anonymous", "observer", "student", "educator")
# Not called blindly: they end the caller's session, or answer 401 for a wrong password by design
# (tested on their own in test_security.py).
SKIP = {
    ("POST", "/api/auth/logout"),
    ("POST", "/api/auth/password"),
    ("POST", "/api/auth/login"),
    ("POST", "/api/auth/token"),
}


def _routes() -> list[tuple[str, str, Perm]]:
    app = create_app(Settings(real_bench=False))
    out = []
    for route, inherited in walk(app.routes):
        if not isinstance(route, APIRoute):
            continue
        perm = permissions_of(route, inherited)[0]
        for method in sorted(route.methods - {"HEAD", "OPTIONS"}):
            if (method, route.path) not in SKIP:
                out.append((method, route.path, perm))
    return out


ROUTES = _routes()


def expected_allowed(role: str, perm: Perm) -> bool:
    if perm is Perm.PUBLIC:
        return True
    if role == "anonymous":
        return False
    if perm is Perm.DRIVE and role == "student":
        return False  # without the bench lease (with it: test_lease.py)
    return perm in ROLE_PERMS[role]


def concrete(path: str) -> str:
    path = re.sub(r"\{[^}]+:path\}", "no-such-file", path)
    return re.sub(r"\{[^}]+\}", "999999", path)


@pytest.fixture(scope="module")
def clients(server, accounts) -> dict[str, httpx.Client]:
    anon = httpx.Client(base_url=server.url, headers={"Origin": server.url}, timeout=30)
    yield {
        "anonymous": anon,
        "observer": accounts["observer"].http,
        "student": accounts["student"].http,
        "educator": server.http,
    }
    anon.close()


@pytest.mark.parametrize("role", ROLES)
@pytest.mark.parametrize(("method", "path", "perm"), ROUTES, ids=[f"{m} {p}" for m, p, _ in ROUTES])
def test_matrix(
    method: str, path: str, perm: Perm, role: str, clients: dict[str, httpx.Client], free_bench: None
) -> None:
    kw: dict[str, Any] = {"json": {}} if method in ("POST", "PUT", "PATCH") else {}
    grpc_web = path.startswith("/rerun.sdk_comms.")  # the live rerun stream (server/http/rerun.py)
    if grpc_web:
        kw = {"content": b"\0" * 5, "headers": {"content-type": "application/grpc-web+proto"}}
    r = clients[role].request(method, concrete(path), **kw)
    if expected_allowed(role, perm):
        # past the check, the made-up method "999999" is refused by the route itself, as gRPC
        passed = r.status_code not in (401, 403) or (grpc_web and r.headers.get("grpc-status") == "7")
        assert passed, f"{role} refused {method} {path} ({perm.value}): {r.status_code} {r.text[:200]}"
        assert r.status_code < 500, r.text[:300]
    else:
        want = 401 if role == "anonymous" else 403
        assert r.status_code == want, f"{role} got {r.status_code} for {method} {path} ({perm.value}): {r.text[:200]}"


def test_matrix_covers_every_permission() -> None:
    assert {p for _, _, p in ROUTES} >= {
        Perm.PUBLIC,
        Perm.SELF,
        Perm.WATCH,
        Perm.STOP,
        Perm.LEASE,
        Perm.DRIVE,
        Perm.EDUCATOR,
    }
