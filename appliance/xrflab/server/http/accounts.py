"""Routes of accounts, sessions, the bench lease and the audit trail; the login page."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import FileResponse, PlainTextResponse
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from ...errors import Busy, Conflict, Denied, Invalid, NotFound, Unavailable, XrfError
from ..security import audit
from ..security.accounts import MAX_PASSWORD, AccountError, User
from ..security.audit import AuditLog
from ..security.auth import (
    CSRF_COOKIE,
    ROLE_PERMS,
    SESSION_COOKIE,
    Perm,
    Security,
    client_address,
    current_user,
    requires,
    set_session_cookies,
)
from ..security.roles import DEFAULT_ROLE, ROLES, Role, role_has

router = APIRouter()

# Proof that a browser logged in to an account before (accounts.LoginGuard); no session in it.
DEVICE_COOKIE = "xrf_device"
DEVICE_COOKIE_MAX_AGE = 180 * 24 * 3600


# ---- models -------------------------------------------------------------------------------------


class Credentials(BaseModel):
    username: str = Field(max_length=64)
    password: str = Field(max_length=MAX_PASSWORD)


class Me(BaseModel):
    id: int
    username: str
    role: Role
    full_name: str
    must_change: bool = Field(description="a one-time password: change it before anything else")
    csrf: str = Field(description="send as X-CSRF-Token with every POST/PUT/PATCH/DELETE made with the cookie")
    perms: list[str]


class ApiToken(BaseModel):
    token: str = Field(description="send as `Authorization: Bearer <token>`; shown once")
    username: str
    role: Role


class PasswordChange(BaseModel):
    current: str = Field(max_length=MAX_PASSWORD)
    new: str = Field(max_length=MAX_PASSWORD)


class UserInfo(BaseModel):
    id: int
    username: str
    role: Role
    full_name: str
    email: str
    disabled: bool
    must_change: bool
    created: float
    last_login: float | None


class NewUser(BaseModel):
    username: str = Field(max_length=64)
    role: Role
    full_name: str = Field(default="", max_length=200)
    email: str = Field(default="", max_length=200)
    password: str | None = Field(
        default=None, max_length=MAX_PASSWORD, description="leave out for a generated one-time password"
    )
    must_change: bool = True


class UserChange(BaseModel):
    role: Role | None = None
    full_name: str | None = Field(default=None, max_length=200)
    email: str | None = Field(default=None, max_length=200)
    disabled: bool | None = None


class UserWithPassword(BaseModel):
    user: UserInfo
    password: str = Field(description="shown once: hand it to the user")


class ClassList(BaseModel):
    csv: str = Field(max_length=1_000_000, description="username,full name,role[,email] per line")


class Imported(BaseModel):
    created: list[UserWithPassword]


class LeaseHolder(BaseModel):
    id: int
    username: str
    role: str
    since: float


class LeaseUser(BaseModel):
    id: int
    username: str
    role: str


class LeaseState(BaseModel):
    event: str
    holder: LeaseHolder | None
    queue: list[LeaseUser]
    idle_s: float
    idle_left_s: float | None


class AuditEntry(BaseModel):
    id: int
    t: float
    user_id: int | None
    username: str
    role: str
    action: str
    detail: Any
    address: str


class Health(BaseModel):
    ok: bool


# ---- helpers ------------------------------------------------------------------------------------


def _sec(request: Request) -> Security:
    return request.app.state.security


def _accounts(request: Request):
    accounts = _sec(request).accounts
    if accounts is None:
        raise Unavailable("the appliance is starting")
    return accounts


def _me(user: User, csrf: str) -> dict[str, Any]:
    perms = sorted(
        p.value for p in Perm if role_has(user.role, p) and not (user.must_change and p not in (Perm.PUBLIC, Perm.SELF))
    )
    return {
        "id": user.id,
        "username": user.username,
        "role": user.role,
        "full_name": user.full_name,
        "must_change": user.must_change,
        "csrf": csrf,
        "perms": perms,
    }


async def _authenticate(request: Request, username: str, password: str) -> User:
    """Password check with the login guard's limits (accounts.LoginGuard); 401 / 429 otherwise."""
    sec = _sec(request)
    accounts = _accounts(request)
    address = client_address(request)
    name = username.strip().lower()
    device = accounts.device_id(name, request.cookies.get(DEVICE_COOKIE))
    wait = sec.login_guard.retry_after(name, address, device)
    if wait > 0:
        audit.record(None, "auth.locked", {"username": username[:64]}, address)
        raise Busy(
            f"too many failed logins; try again in {int(wait) + 1} s", headers={"Retry-After": str(int(wait) + 1)}
        )
    async with sec.hash_slots:
        user = await run_in_threadpool(accounts.verify, username, password)
    if user is None:
        sec.login_guard.failed(name, address, device)
        audit.record(None, "auth.failed", {"username": username[:64]}, address)
        raise XrfError("wrong username or password", 401)
    sec.login_guard.succeeded(name, address, device)
    return user


# ---- pages and health ---------------------------------------------------------------------------


@router.get("/login", include_in_schema=False, dependencies=[requires(Perm.PUBLIC)])
async def login_page(request: Request) -> FileResponse:
    page = request.app.state.settings.frontend_dir / "login.html"
    if not page.is_file():
        raise NotFound("no login page in this install; use POST /api/auth/login")
    return FileResponse(page, headers={"Cache-Control": "no-cache"})


@router.get("/api/health", response_model=Health, dependencies=[requires(Perm.PUBLIC)])
async def health() -> dict[str, Any]:
    return {"ok": True}


# ---- login, sessions, tokens --------------------------------------------------------------------


@router.post(
    "/api/auth/login",
    response_model=Me,
    dependencies=[requires(Perm.PUBLIC)],
    responses={401: {"description": "wrong username or password"}, 429: {"description": "rate limited"}},
)
async def login(body: Credentials, request: Request, response: Response) -> dict[str, Any]:
    user = await _authenticate(request, body.username, body.password)
    accounts = _accounts(request)
    token, csrf = accounts.new_session(user, client_address(request))
    set_session_cookies(request, response, token, csrf, int(accounts.session_max_s))
    # This browser now knows the password: its later logins are counted apart (LoginGuard).
    response.set_cookie(
        DEVICE_COOKIE,
        accounts.new_device_cookie(user),
        max_age=DEVICE_COOKIE_MAX_AGE,
        path="/api/auth",
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
    )
    audit.record(user, "auth.login", {"via": "password"}, client_address(request))
    return _me(user, csrf)


@router.post("/api/auth/logout", status_code=204, dependencies=[requires(Perm.SELF)])
async def logout(request: Request, user: User = Depends(current_user)) -> Response:
    session = request.scope.get("xrf_session")
    if session:
        _accounts(request).end_session(session)
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/")
    response.delete_cookie(CSRF_COOKIE, path="/")
    audit.record(user, "auth.logout", {}, client_address(request))
    return response


@router.get("/api/me", response_model=Me, dependencies=[requires(Perm.SELF)])
async def me(request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    return _me(user, _sec(request).resolve(request)[2])


class RoleInfo(BaseModel):
    name: Role
    perms: list[str] = Field(description="what the role may do (server/security/roles.py's Perm values)")


class Roles(BaseModel):
    roles: list[RoleInfo]
    default: Role = Field(description="the role offered first for a new account")


@router.get("/api/roles", response_model=Roles, dependencies=[requires(Perm.WATCH)])
async def roles() -> dict[str, Any]:
    """Every role and its permissions (server/security/roles.py): the Users page's role menus list
    these; pages decide what to show by /api/me's `perms`, never by a role's name."""
    return {
        "roles": [{"name": r, "perms": sorted(p.value for p in ROLE_PERMS[r])} for r in ROLES],
        "default": DEFAULT_ROLE,
    }


@router.post(
    "/api/auth/password",
    status_code=204,
    dependencies=[requires(Perm.SELF)],
    responses={401: {"description": "wrong current password"}, 422: {"description": "new password refused"}},
)
async def change_password(body: PasswordChange, request: Request, user: User = Depends(current_user)) -> Response:
    await _authenticate(request, user.username, body.current)
    accounts = _accounts(request)
    if body.new == body.current:
        raise Invalid("the new password must differ from the current one")
    await run_in_threadpool(accounts.set_password, user.id, body.new, False)  # AccountError: 422
    # set_password ended every session and token; a browser gets a fresh session.
    response = Response(status_code=204)
    if request.scope.get("xrf_session"):
        token, csrf = accounts.new_session(user, client_address(request))
        set_session_cookies(request, response, token, csrf, int(accounts.session_max_s))
    audit.record(user, "user.password", {"user": user.username}, client_address(request))
    return response


@router.post(
    "/api/auth/token",
    response_model=ApiToken,
    dependencies=[requires(Perm.PUBLIC)],
    responses={401: {"description": "wrong username or password"}, 429: {"description": "rate limited"}},
)
async def api_token(body: Credentials, request: Request) -> dict[str, Any]:
    """An API token for the CLI (`xrf login`); replaces the user's previous one."""
    user = await _authenticate(request, body.username, body.password)
    if user.must_change:
        raise Denied("change your one-time password in the dashboard first")
    token = _accounts(request).new_api_token(user)
    audit.record(user, "auth.token", {}, client_address(request))
    return {"token": token, "username": user.username, "role": user.role}


@router.delete("/api/auth/token", status_code=204, dependencies=[requires(Perm.SELF)])
async def drop_api_token(request: Request, user: User = Depends(current_user)) -> Response:
    _accounts(request).drop_api_token(user.id)
    audit.record(user, "auth.token_revoked", {}, client_address(request))
    return Response(status_code=204)


# ---- users (educators) --------------------------------------------------------------------------


@router.get("/api/users", response_model=list[UserInfo], dependencies=[requires(Perm.EDUCATOR)])
async def list_users(request: Request) -> list[dict[str, Any]]:
    return [u.public() for u in _accounts(request).list()]


@router.post("/api/users", response_model=UserWithPassword, status_code=201, dependencies=[requires(Perm.EDUCATOR)])
async def create_user(body: NewUser, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    created, password = await run_in_threadpool(
        _accounts(request).create,
        body.username,
        body.role,
        body.password,
        body.full_name,
        body.email,
        body.must_change,
    )
    audit.record(user, "user.create", {"user": created.username, "role": created.role}, client_address(request))
    return {"user": created.public(), "password": password}


@router.post("/api/users/import", response_model=Imported, status_code=201, dependencies=[requires(Perm.EDUCATOR)])
async def import_users(body: ClassList, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    accounts = _accounts(request)
    rows = accounts.parse_class_list(body.csv)
    if len(rows) > 500:
        raise Invalid("at most 500 accounts per class list")
    created: list[dict[str, Any]] = []
    for r in rows:
        try:
            u, password = await run_in_threadpool(
                accounts.create, r["username"], r["role"], None, r["full_name"], r["email"]
            )
        except AccountError as exc:  # taken since parsing (a concurrent create): say so, keep the rest
            raise Conflict(f"{r['username']}: {exc}; {len(created)} accounts were created before") from None
        created.append({"user": u.public(), "password": password})
    audit.record(user, "user.import", {"users": [c["user"]["username"] for c in created]}, client_address(request))
    return {"created": created}


def _guard_last_educator(request: Request, target: User, change: UserChange) -> None:
    accounts = _accounts(request)
    demoted = change.role is not None and not role_has(change.role, Perm.EDUCATOR)
    if (
        target.is_educator
        and not target.disabled
        and (change.disabled or demoted)
        and accounts.educators_enabled() <= 1
    ):
        raise Conflict("this is the last enabled educator account")


@router.patch("/api/users/{user_id}", response_model=UserInfo, dependencies=[requires(Perm.EDUCATOR)])
async def change_user(
    user_id: int, body: UserChange, request: Request, user: User = Depends(current_user)
) -> dict[str, Any]:
    accounts = _accounts(request)
    target = accounts.get(user_id)
    if target is None:
        raise NotFound(f"no user {user_id}")
    if target.id == user.id and (body.disabled or (body.role is not None and body.role != user.role)):
        raise Conflict("you cannot disable your own account or change your own role")
    _guard_last_educator(request, target, body)
    changed = accounts.update(user_id, **body.model_dump(exclude_none=True))
    lease = _sec(request).lease
    if changed.disabled or changed.role != target.role:  # their sessions ended: so do their sockets
        _sec(request).disconnect(user_id)
        if lease is not None:
            lease.forget(user_id, "account disabled" if changed.disabled else "role changed")
    audit.record(
        user, "user.update", {"user": changed.username, **body.model_dump(exclude_none=True)}, client_address(request)
    )
    return changed.public()


@router.post("/api/users/{user_id}/reset", response_model=UserWithPassword, dependencies=[requires(Perm.EDUCATOR)])
async def reset_user(user_id: int, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    accounts = _accounts(request)
    password = await run_in_threadpool(accounts.set_password, user_id, None)
    target = accounts.get(user_id)
    assert target is not None
    _sec(request).disconnect(user_id)
    audit.record(user, "user.reset", {"user": target.username}, client_address(request))
    return {"user": target.public(), "password": password}


# ---- the bench lease ----------------------------------------------------------------------------


def _lease(request: Request):
    lease = _sec(request).lease
    if lease is None:
        raise Unavailable("the appliance is starting")
    return lease


@router.get("/api/lease", response_model=LeaseState, dependencies=[requires(Perm.WATCH)])
async def get_lease(request: Request) -> dict[str, Any]:
    return _lease(request).payload()


def _lease_action(name: str):
    async def action(request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
        return getattr(_lease(request), name)(user)  # a refusal is a LeaseError (an XrfError)

    return action


for _path, _method, _doc in (
    ("take", "take", "Take the free bench; an educator takes it over from its holder."),
    ("release", "release", "Give the bench back (the holder, or an educator for anyone); the queue moves up."),
    ("queue", "enqueue", "Wait for the bench; taken at once when it is free."),
    ("leave", "leave_queue", "Leave the queue."),
):
    router.add_api_route(
        f"/api/lease/{_path}",
        _lease_action(_method),
        methods=["POST"],
        response_model=LeaseState,
        dependencies=[requires(Perm.LEASE)],
        description=_doc,
        name=f"lease_{_path}",
    )


# ---- audit (educators) --------------------------------------------------------------------------


def _audit_rows(
    request: Request,
    username: str | None,
    action: str | None,
    since: float | None,
    until: float | None,
    limit: int,
    offset: int,
) -> list[dict[str, Any]]:
    return _audit_log(request).query(username, action, since, until, limit, offset)


def _audit_log(request: Request) -> AuditLog:
    log = _sec(request).audit
    if log is None:
        raise Unavailable("the appliance is starting")
    return log


@router.get("/api/audit", response_model=list[AuditEntry], dependencies=[requires(Perm.EDUCATOR)])
async def get_audit(
    request: Request,
    username: str | None = Query(None, max_length=64),
    action: str | None = Query(None, max_length=100, description="an action or its prefix: lease, run, user.create"),
    since: float | None = Query(None, description="Unix time"),
    until: float | None = Query(None, description="Unix time"),
    limit: int = Query(200, ge=1, le=10000),
    offset: int = Query(0, ge=0, le=10**9),
) -> list[dict[str, Any]]:
    return _audit_rows(request, username, action, since, until, limit, offset)


@router.get("/api/audit.csv", response_class=PlainTextResponse, dependencies=[requires(Perm.EDUCATOR)])
async def export_audit(
    request: Request,
    username: str | None = Query(None, max_length=64),
    action: str | None = Query(None, max_length=100),
    since: float | None = None,
    until: float | None = None,
    limit: int = Query(100000, ge=1, le=1000000),
) -> PlainTextResponse:
    rows = _audit_rows(request, username, action, since, until, limit, 0)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return PlainTextResponse(
        _audit_log(request).to_csv(rows),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="xrf-audit-{stamp}.csv"'},
    )
