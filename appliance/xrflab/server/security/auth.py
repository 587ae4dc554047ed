"""Permissions: every HTTP route and every WebSocket message type declares the one it needs.

Routes declare theirs with ``dependencies=[requires(Perm.X)]``; a test (tests/server/accounts/
test_route_table.py) walks the route table and fails for any route without one. WebSocket
message types are declared in server/http/runs.py's ``WS_PERMS``. ``check()`` resolves the user (session
cookie or ``Authorization: Bearer`` API token), enforces CSRF on state-changing requests made with
the cookie, and the role's permissions, including the bench lease for DRIVE.

How to protect a new endpoint: docs/developers/security.md.
"""

from __future__ import annotations

import asyncio
import hmac
import time
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from fastapi import Depends, Response
from starlette.exceptions import WebSocketException
from starlette.requests import HTTPConnection

from ...channels import names as _names
from ...errors import XrfError
from .accounts import Accounts, LoginGuard, User
from .roles import ROLE_PERMS, Perm, role_has

if TYPE_CHECKING:
    from ..settings import Settings
    from .audit import AuditLog
    from .lease import Lease

__all__ = ["Perm", "ROLE_PERMS", "User", "check", "requires", "current_user", "owns", "Security", "SAFE_COMMANDS"]

SESSION_COOKIE = "xrf_session"
CSRF_COOKIE = "xrf_csrf"
CSRF_HEADER = "x-csrf-token"
UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# Commands anyone who may stop (student and up) sends without holding the lease: stopping is safe.
# Which ones is a property of the command: channels.h's XRF_CMDS says (stop, pause).
SAFE_COMMANDS = _names.SAFE_COMMANDS


class Security:
    """Everything check() needs, hung on app.state.security: accounts, lease, audit, limits."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.accounts: Accounts | None = None
        self.lease: Lease | None = None
        self.audit: AuditLog | None = None
        self.hub: Any = None
        self.login_guard = LoginGuard(
            settings.login_max_failures,
            settings.login_max_failures_address,
            settings.login_max_failures_account,
            settings.login_window_s,
            settings.login_lock_s,
        )
        # argon2 is memory-hard on purpose: at most this many checks at once (a login rush on a Pi).
        self.hash_slots = asyncio.Semaphore(4)

    def open(self, hub: Any) -> None:
        """In the app's lifespan, once the hub exists: the lease publishes on it, and a user whose
        sessions end is disconnected from it. The app (server/app.py) wires the rest: the lease's
        snapshot for new clients and the ownership rule of the hub's fan-out."""
        from . import audit as auditmod
        from .audit import AuditLog
        from .lease import Lease

        settings = self.settings
        self.accounts = Accounts(settings.accounts_db, settings.session_max_s, settings.session_idle_s)
        self.audit = AuditLog(settings.audit_db)
        auditmod.use(self.audit)
        lease = Lease(settings.lease_idle_s, hub.publish, auditmod.record)
        self.lease = lease
        bootstrap_admin(self.accounts)
        self.hub = hub
        lease.start()

    def disconnect(self, user_id: int) -> None:
        """Close the WebSockets of a user whose sessions just ended (disabled, reset)."""
        if self.hub is not None:
            self.hub.disconnect_user(user_id, "your session ended")

    def close(self) -> None:
        from . import audit as auditmod

        if self.lease is not None:
            self.lease.stop()
        auditmod.use(None)
        for db in (self.audit, self.accounts):
            if db is not None:
                db.close()

    # -- origins ----------------------------------------------------------------------------------

    def allowed_origins(self, conn: HTTPConnection) -> set[str]:
        scheme = "https" if conn.url.scheme in ("https", "wss") else "http"
        host = conn.headers.get("host", "")
        return {f"{scheme}://{host}".lower()} | {o.rstrip("/").lower() for o in self.settings.allow_origins}

    def origin_ok(self, conn: HTTPConnection, require: bool) -> bool:
        """Origin (or else Referer) names this appliance or an allowed origin. Browsers send Origin
        with every POST and WebSocket handshake; a request with neither passes only if not `require`d."""
        origin = conn.headers.get("origin")
        if origin is None:
            referer = conn.headers.get("referer")
            if referer is None:
                return not require
            parts = urlsplit(referer)
            origin = f"{parts.scheme}://{parts.netloc}"
        return origin.rstrip("/").lower() in self.allowed_origins(conn)

    # -- who is asking ----------------------------------------------------------------------------

    def resolve(self, conn: HTTPConnection) -> tuple[User | None, str, str]:
        """(user, how: "cookie" | "bearer" | "", csrf of the session). Cached per request."""
        cached = conn.scope.get("xrf_auth")
        if cached is not None:
            return cached
        result: tuple[User | None, str, str] = (None, "", "")
        accounts = self.accounts
        if accounts is not None:
            authz = conn.headers.get("authorization", "")
            if authz[:7].lower() == "bearer ":
                user = accounts.api_token_user(authz[7:].strip())
                result = (user, "bearer" if user else "", "")
            else:
                token = conn.cookies.get(SESSION_COOKIE, "")
                session = accounts.session(token) if token else None
                if session is not None:
                    result = (session.user, "cookie", session.csrf)
                    conn.scope["xrf_session"] = session.token_hash
        conn.scope["xrf_auth"] = result
        return result

    def resolve_link(self, conn: HTTPConnection, link: str, scope: str) -> User | None:
        """A request that carries a link (accounts.new_link) instead of a login: it acts as the
        link's user for this request only (routes declared Perm.PUBLIC that take one)."""
        user = self.accounts.link_user(link, scope) if self.accounts is not None else None
        conn.scope["xrf_auth"] = (user, "link" if user else "", "")
        return user


def _deny(conn: HTTPConnection, status: int, detail: str) -> Exception:
    if conn.scope["type"] == "websocket":
        return WebSocketException(code=1008, reason=detail[:120])
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return XrfError(detail, status, headers=headers)  # 401 or 403, answered by server/http/errors.py


def set_session_cookies(conn: HTTPConnection, response: Response, token: str, csrf: str, max_age: int) -> None:
    """A new session's cookies on `response`: the session (HTTP only) and its CSRF token. For every
    way of logging in: the password (server/http/accounts.py), a changed password, the room's
    sign-on link (room/bench.py)."""
    secure = conn.url.scheme == "https"
    response.set_cookie(
        SESSION_COOKIE, token, max_age=max_age, path="/", httponly=True, samesite="strict", secure=secure
    )
    # Readable by the page (double submit: the page copies it into X-CSRF-Token); it is also
    # bound to the session on the server, so a cookie planted by someone else is useless.
    response.set_cookie(CSRF_COOKIE, csrf, max_age=max_age, path="/", httponly=False, samesite="strict", secure=secure)


def may(user: User, perm: Perm, lease: Lease | None = None) -> bool:
    """The role allows `perm`; for a student's DRIVE, only while holding the lease."""
    if not role_has(user.role, perm):
        return False
    if perm is Perm.DRIVE and not user.is_educator:
        return lease is not None and lease.holds(user)
    return True


def check(conn: HTTPConnection, perm: Perm, *, grpc_web: bool = False) -> User | None:
    """Raise (XrfError 401/403, or WebSocketException on a handshake) when the request may not do
    `perm`; return the user (None for an anonymous PUBLIC request). `grpc_web`: see
    requires_grpc_web()."""
    security: Security = conn.app.state.security
    user, how, csrf = security.resolve(conn)
    method = conn.scope.get("method", "GET")
    is_ws = conn.scope["type"] == "websocket"
    if perm is Perm.PUBLIC:
        # A public POST (the login) still refuses a foreign page posting to it (login CSRF).
        if method in UNSAFE_METHODS and not security.origin_ok(conn, require=False):
            raise _deny(conn, 403, "cross-site request refused (Origin)")
        return user
    if user is None:
        raise _deny(conn, 401, "log in first")
    if is_ws and not security.origin_ok(conn, require=how == "cookie"):
        raise _deny(conn, 403, "WebSocket from a foreign origin refused")
    if how == "cookie" and method in UNSAFE_METHODS:
        if not security.origin_ok(conn, require=True):
            raise _deny(conn, 403, "cross-site request refused (Origin/Referer)")
        if grpc_web:
            if not is_grpc_web(conn):
                raise _deny(conn, 403, "a gRPC-web request (Content-Type application/grpc-web) was expected")
        else:
            sent = conn.headers.get(CSRF_HEADER, "")
            if not sent or not hmac.compare_digest(sent.encode(), csrf.encode()):
                raise _deny(conn, 403, "missing or wrong CSRF token (X-CSRF-Token)")
    if user.must_change and perm is not Perm.SELF:
        raise _deny(conn, 403, "change your password first (POST /api/auth/password)")
    if perm is Perm.DRIVE and role_has(user.role, perm) and not may(user, perm, security.lease):
        holder = security.lease.holder if security.lease else None
        who = f"{holder.user.username} holds it" if holder else "nobody holds it; take it first"
        raise _deny(conn, 403, f"you do not hold the bench ({who})")
    if not may(user, perm, security.lease):
        raise _deny(conn, 403, f"{user.role}s may not do this (needs {perm.value})")
    if perm is Perm.DRIVE and security.lease is not None:
        security.lease.touch(user)
    return user


def requires(perm: Perm) -> Any:
    async def dependency(conn: HTTPConnection) -> None:
        check(conn, perm)

    # read by the route-table test (a function attribute: FastAPI keeps the dependency callable)
    setattr(dependency, "xrf_permission", perm)  # noqa: B010
    return Depends(dependency)


def is_grpc_web(conn: HTTPConnection) -> bool:
    ctype = conn.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    return ctype in ("application/grpc-web", "application/grpc-web+proto")


def requires_grpc_web(perm: Perm) -> Any:
    """requires() for the read-only gRPC-web calls of rerun's viewer, which cannot add our CSRF
    header to its POSTs. What stands in for the token: a same-origin Origin (required, as for
    every cookie POST), a gRPC-web content type (no HTML form can send it, and a cross-site
    fetch with it needs a CORS preflight, which the appliance never grants) and the
    SameSite=Strict session cookie. Use it only for calls that change nothing."""

    async def dependency(conn: HTTPConnection) -> None:
        check(conn, perm, grpc_web=True)

    # read by the route-table test (a function attribute: FastAPI keeps the dependency callable)
    setattr(dependency, "xrf_permission", perm)  # noqa: B010
    return Depends(dependency)


def current_user(conn: HTTPConnection) -> User:
    """Dependency: the logged-in user (after the route's requires() has let the request in).
    ``user: User = Depends(current_user)``."""
    security: Security = conn.app.state.security
    user, _, _ = security.resolve(conn)
    if user is None:
        raise _deny(conn, 401, "log in first")
    return user


def optional_user(conn: HTTPConnection) -> User | None:
    security: Security = conn.app.state.security
    return security.resolve(conn)[0]


def owns(user: User | HTTPConnection, owner: int | str | None) -> bool:
    """May `user` see/change a resource owned by `owner` (a user id, or a username as in the runs
    table's `owner` column)? Educators: everything; everyone else: their own only (resources
    without an owner belong to the educators). `user` may also be the request itself.
    Routes and the WebSocket use it through server/security/ownership.py (the 404, lists, the live run)."""
    who: User | None = user.app.state.security.resolve(user)[0] if isinstance(user, HTTPConnection) else user
    if who is None:
        return False
    if who.is_educator:
        return True
    if owner is None or owner == "":
        return False
    if isinstance(owner, str):  # usernames may be all digits (student numbers): a str is a name
        return owner.strip().lower() == who.username
    return owner == who.id


def client_address(conn: HTTPConnection) -> str:
    return conn.client.host if conn.client else ""


def now() -> float:
    return time.time()


def bootstrap_admin(accounts: Accounts) -> None:
    """First start (no account at all): an educator `admin` with a one-time secret, printed once
    to the console (the journal under systemd) and never stored in clear. It must be changed at
    the first login. XRF_BOOTSTRAP_ADMIN_PASSWORD sets the password instead: for the test
    harness only (no change required); there is no default password."""
    import os

    from . import audit as auditmod

    if accounts.count() > 0:
        return
    given = os.environ.get("XRF_BOOTSTRAP_ADMIN_PASSWORD")
    if given:
        accounts.create("admin", "educator", given, full_name="Administrator", must_change=False)
        auditmod.record(None, "user.create", {"user": "admin", "role": "educator", "bootstrap": "environment"})
        return
    _, secret = accounts.create("admin", "educator", None, full_name="Administrator")
    auditmod.record(None, "user.create", {"user": "admin", "role": "educator", "bootstrap": "one-time secret"})
    print("XRF Lab: first start: created the educator account 'admin' with the one-time password", flush=True)
    print(f"XRF Lab:     {secret}", flush=True)
    print("XRF Lab: log in with it and choose a new password; it is not shown again.", flush=True)


class SecurityHeaders:
    """ASGI middleware: nosniff, no framing by other sites, no Referer to other sites. (Pure ASGI,
    not BaseHTTPMiddleware: streamed responses and the WebSocket pass through untouched.)"""

    HEADERS = [
        (b"x-content-type-options", b"nosniff"),
        (b"x-frame-options", b"SAMEORIGIN"),
        (b"referrer-policy", b"same-origin"),
    ]

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Any) -> None:
            if message["type"] == "http.response.start":
                have = {k.lower() for k, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []), *(h for h in self.HEADERS if h[0] not in have)]
            await send(message)

        await self.app(scope, receive, send_with_headers)
