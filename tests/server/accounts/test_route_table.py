"""Every endpoint declares its permission: each HTTP and WebSocket route of the app carries a
`requires(Perm.X)` dependency, and every WebSocket message type is in api.WS_PERMS. A route
added without one fails here (and so the build)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from fastapi.routing import APIRoute, APIWebSocketRoute
from starlette.routing import Mount

from xrflab.server.app import create_app
from xrflab.server.http import runs as api
from xrflab.server.security.auth import Perm
from xrflab.server.settings import Settings

# Mounts serve files and carry no dependencies: each one is listed here with why it may be public.
PUBLIC_MOUNTS = {
    "/static": "the dashboard's code and styles; no data",
    "/static/vendor/codemirror": "Debian's CodeMirror, the editor's code; no data",
}


def walk(routes: list[Any], inherited: tuple[Any, ...] = ()) -> Iterator[tuple[Any, tuple[Any, ...]]]:
    """(route, dependencies inherited from include_router) for every route, however nested.
    FastAPI >= 0.120 keeps included routers as _IncludedRouter nodes instead of copying routes."""
    for route in routes:
        original = getattr(route, "original_router", None)
        if original is not None:
            deps = inherited + tuple(route.include_context.dependencies or ())
            yield from walk(list(original.routes), deps)
        else:
            yield route, inherited


def permissions_of(route: Any, inherited: tuple[Any, ...]) -> list[Perm]:
    calls = [d.call for d in route.dependant.dependencies] + [d.dependency for d in inherited]
    return [c.xrf_permission for c in calls if hasattr(c, "xrf_permission")]


def all_routes(tmp_path) -> list[tuple[Any, tuple[Any, ...]]]:
    app = create_app(Settings(data_dir=tmp_path, real_bench=False))
    return list(walk(app.routes))


def test_every_route_declares_a_permission(tmp_path) -> None:
    missing, seen = [], 0
    for route, inherited in all_routes(tmp_path):
        if isinstance(route, (APIRoute, APIWebSocketRoute)):
            seen += 1
            perms = permissions_of(route, inherited)
            if len(perms) != 1:
                methods = ",".join(sorted(getattr(route, "methods", None) or {"WS"}))
                missing.append(f"{methods} {route.path}: {perms or 'no requires(Perm.X)'}")
        elif isinstance(route, Mount):
            assert route.path in PUBLIC_MOUNTS, f"mount {route.path} is not a known public mount"
        else:
            raise AssertionError(f"unexpected route type {type(route).__name__} at {getattr(route, 'path', '?')}")
    assert seen > 20
    assert not missing, "routes without exactly one requires(Perm.X):\n" + "\n".join(missing)


def test_api_routes_are_not_public_except_the_login_ones(tmp_path) -> None:
    public = {
        route.path
        for route, inh in all_routes(tmp_path)
        if isinstance(route, (APIRoute, APIWebSocketRoute)) and Perm.PUBLIC in permissions_of(route, inh)
    }
    # /room/sso is a sign-in route too: a bench enrolled in a lab room takes the room's signed,
    # short-lived token as the credential (room/sso.py); without a valid one it answers 403/404.
    # /favicon.ico: a locally drawn icon, no data (the login page shows it too).
    assert public == {
        "/",
        "/login",
        "/favicon.ico",
        "/api/health",
        "/api/auth/login",
        "/api/auth/token",
        "/room/sso",
        # rerun's web viewer fetches a finished run's .rrd without the cookie: the link in the path
        # is the credential (accounts.new_link: one user, one log, an hour; else 404).
        "/api/logs/viewer/{link}/{run_id}/{name:path}",
    }, public


def test_websocket_message_table() -> None:
    assert set(api.WS_PERMS) >= {"command", "setpoint", "subscribe", "ping"}
    assert all(isinstance(p, Perm) for p in api.WS_PERMS.values())
    assert api.WS_PERMS["setpoint"] is Perm.DRIVE
    assert api.WS_PERMS["command"] is Perm.STOP  # stop/pause for everyone but observers; others DRIVE


def test_unlisted_message_types_are_refused(server, accounts) -> None:
    """The handler looks a type up in WS_PERMS before anything else: an unlisted type is refused."""
    with server.ws() as ws:
        ws.send({"type": "drive_everything", "id": 7})
        reply = ws.wait_type("error")
        assert "unknown message type" in reply["error"] and reply["id"] == 7
