"""The one error type (xrflab/errors.py) and its one handler (server/http/errors.py), in process:
a service raises an XrfError kind, the client gets its status, ``{"detail": ...}`` (FastAPI's own
shape, so the wire is what HTTPException answered before) and its headers; and, read from the
source, no module outside the routes raises fastapi's HTTPException and no route catches a
service's error only to translate it by hand."""

from __future__ import annotations

import ast
import asyncio
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from xrflab import errors
from xrflab.logs.reader import LogFormatError
from xrflab.profiles import FieldError, ProfileError, ProfileNotFound
from xrflab.projects.archive import ArchiveRejected
from xrflab.selfcheck import BenchBusy, SelfCheckError
from xrflab.server.http import errors as http_errors
from xrflab.server.runs.run import SupervisorError
from xrflab.server.security.accounts import AccountError
from xrflab.server.security.lease import LeaseError

PACKAGE = Path(errors.__file__).resolve().parent
ROUTES = PACKAGE / "server" / "http"


def _client(exc: Exception) -> TestClient:
    """A tiny app with the handler installed whose one route raises `exc`, as a service would."""
    app = FastAPI()
    http_errors.install(app)

    def service() -> None:
        raise exc

    @app.get("/x")
    async def route() -> None:
        service()

    @app.get("/sync")
    def sync_route() -> None:  # run in a thread pool: the handler answers there too
        service()

    return TestClient(app, raise_server_exceptions=False)


@pytest.mark.parametrize(
    ("exc", "status", "body"),
    [
        (errors.Invalid("bad field"), 422, {"detail": "bad field"}),
        (errors.Denied("not yours"), 403, {"detail": "not yours"}),
        (errors.NotFound("no run 7"), 404, {"detail": "no run 7"}),
        (errors.Conflict("a run is active"), 409, {"detail": "a run is active"}),
        (errors.TooLarge("over 1 MB"), 413, {"detail": "over 1 MB"}),
        (errors.Unavailable("the appliance is starting"), 503, {"detail": "the appliance is starting"}),
        (errors.XrfError("wrong username or password", 401), 401, {"detail": "wrong username or password"}),
        (errors.NotFound("moved", 410), 410, {"detail": "moved"}),
        # The services' own errors, with the statuses their routes answered by hand before.
        (SupervisorError("no run is active"), 409, {"detail": "no run is active"}),
        (SupervisorError("no build named 'x'", 404), 404, {"detail": "no build named 'x'"}),
        (AccountError("role 'x': one of educator"), 422, {"detail": "role 'x': one of educator"}),
        (AccountError("username 'a' is taken", 409), 409, {"detail": "username 'a' is taken"}),
        (LeaseError("nobody holds the bench"), 409, {"detail": "nobody holds the bench"}),
        (LeaseError("the bench is held by a, not you", 403), 403, {"detail": "the bench is held by a, not you"}),
        (LogFormatError("f.xrf: not a log"), 422, {"detail": "f.xrf: not a log"}),
        (SelfCheckError("unknown transport 'x'"), 422, {"detail": "unknown transport 'x'"}),
        (
            BenchBusy("a loop is running on the bench: stop it first"),
            409,
            {"detail": "a loop is running on the bench: stop it first"},
        ),
        (
            ArchiveRejected("a link", "src/x"),
            422,
            {"detail": {"error": "archive refused: src/x: a link", "entry": "src/x", "message": "a link"}},
        ),
        (
            ProfileError([FieldError("channel 1.duty", "over 100"), "no name"], "p.json"),
            422,
            {
                "detail": {
                    "message": "p.json: over 100; no name",
                    "errors": [{"field": "channel 1.duty", "message": "over 100"}, {"field": "", "message": "no name"}],
                }
            },
        ),
        (ProfileNotFound(["no bench profile named 'q'"]), 404, {"detail": "no bench profile named 'q'"}),
    ],
)
@pytest.mark.parametrize("path", ["/x", "/sync"])
def test_a_service_error_is_its_status_and_body(exc: Exception, status: int, body: dict, path: str) -> None:
    r = _client(exc).get(path)
    assert (r.status_code, r.json()) == (status, body)


def test_typed_detail_and_headers() -> None:
    r = _client(errors.Invalid("two problems", detail={"errors": [1, 2]})).get("/x")
    assert (r.status_code, r.json()) == (422, {"detail": {"errors": [1, 2]}})
    r = _client(errors.Busy("try again in 3 s", headers={"Retry-After": "3"})).get("/x")
    assert (r.status_code, r.json(), r.headers["retry-after"]) == (429, {"detail": "try again in 3 s"}, "3")


def test_the_message_stays_the_logs_and_str() -> None:
    exc = ArchiveRejected("a link", "src/x")
    assert str(exc) == "src/x: a link" and exc.message == "a link" and exc.entry == "src/x"
    # Still what their other callers catch them as.
    assert isinstance(LogFormatError("x"), ValueError) and isinstance(ProfileError(["x"]), ValueError)
    assert isinstance(SelfCheckError("x"), RuntimeError)


def test_a_file_name_that_is_not_utf8_still_answers() -> None:
    """A log's path from the file system may hold a lone surrogate; JSON cannot carry it."""
    r = _client(LogFormatError("run/\udcff.xrf: not a log")).get("/x")
    assert (r.status_code, r.json()) == (422, {"detail": "run/\\udcff.xrf: not a log"})


def test_the_appliance_installs_the_handler(tmp_path: Path) -> None:
    from xrflab.server.app import create_app
    from xrflab.server.settings import Settings

    app = create_app(Settings(data_dir=tmp_path / "data", frontend_dir=tmp_path, real_bench=False))
    # No lifespan (nothing started): a public route whose page is missing raises NotFound.
    r = TestClient(app).get("/login")
    assert (r.status_code, r.json()) == (404, {"detail": "no login page in this install; use POST /api/auth/login"})


# ---- the WebSocket: a service's XrfError is an `error` reply with its message ---------------------


class _Client:
    """What /ws's message handler uses of a hub client: its socket (the app's security) and replies."""

    def __init__(self, user: Any) -> None:
        security = SimpleNamespace(resolve=lambda ws: (user, None, None), lease=None)
        self.ws = SimpleNamespace(app=SimpleNamespace(state=SimpleNamespace(security=security)), scope={}, client=None)
        self.user = user
        self.replies: list[Any] = []
        self.kick_reason = ""
        self.kicked = asyncio.Event()

    def reply(self, message: Any) -> None:
        self.replies.append(message.model_dump(exclude_none=True))


class _Supervisor:
    async def command(self, cmd: Any) -> Any:
        raise SupervisorError("no run is active; start one first")

    def setpoint(self, fields: dict[str, Any]) -> dict[str, Any]:
        raise LeaseError("the bench is held by a, not you", 403)


def _ws(user: Any, message: dict[str, Any]) -> _Client:
    from xrflab.server.http.runs import _handle

    client = _Client(user)
    asyncio.run(_handle(json.dumps(message), client, _Supervisor()))  # type: ignore[arg-type]
    return client


def test_ws_answers_a_service_error_with_its_message() -> None:
    from xrflab.server.security.accounts import User

    educator = User(id=1, username="e", role="educator")
    c = _ws(educator, {"type": "command", "cmd": "stop", "id": 5})
    assert c.replies == [{"type": "error", "id": 5, "request": "command", "error": "no run is active; start one first"}]
    # 403: refused for want of a permission, so flagged `denied`; the connection carries on.
    c = _ws(educator, {"type": "setpoint", "fields": {"x": 1}, "id": 6})
    assert c.replies == [
        {"type": "error", "id": 6, "request": "setpoint", "error": "the bench is held by a, not you", "denied": True}
    ]
    assert not c.kicked.is_set()


def test_ws_a_session_gone_is_denied_and_closes() -> None:
    c = _ws(None, {"type": "ping", "id": 1})
    assert c.replies == [
        {"type": "error", "id": 1, "request": "ping", "error": "your session ended; log in again", "denied": True}
    ]
    assert c.kicked.is_set() and c.kick_reason == "your session ended; log in again"


# ---- the source: nobody else answers HTTP, no route translates ---------------------------------

# Modules not converted yet, each with a note; the lists only shrink. Everything else raises an
# xrflab.errors kind (or a service's XrfError) and lets server/http/errors.py answer.
HTTP_EXCEPTION_OUTSIDE_ROUTES: set[str] = set()  # none: every service raises an xrflab.errors kind
TRANSLATING_ROUTES: set[str] = set()  # none: every route lets the XrfError through


def _modules(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*.py") if "__pycache__" not in p.parts)


def test_no_module_outside_the_routes_raises_http_exception() -> None:
    found = {
        p.relative_to(PACKAGE).as_posix()
        for p in _modules(PACKAGE)
        if ROUTES not in p.parents and "HTTPException" in p.read_text(encoding="utf-8")
    }
    assert found <= HTTP_EXCEPTION_OUTSIDE_ROUTES, (
        f"{sorted(found - HTTP_EXCEPTION_OUTSIDE_ROUTES)}: raise an xrflab.errors kind, not fastapi's HTTPException"
    )


def _translations(path: Path) -> list[str]:
    """`except <X>Error` handlers whose body raises an HTTPException: a translation by hand."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.ExceptHandler) or node.type is None:
            continue
        caught = [n for n in ast.walk(node.type) if isinstance(n, (ast.Name, ast.Attribute))]
        names = [n.id if isinstance(n, ast.Name) else n.attr for n in caught]
        if not any(name.endswith(("Error", "Rejected", "NotFound")) for name in names):
            continue
        for inner in ast.walk(node):
            if isinstance(inner, ast.Raise) and inner.exc is not None and "HTTPException" in ast.unparse(inner.exc):
                out.append(f"{path.name}:{node.lineno} except {ast.unparse(node.type)}")
    return out


def test_routes_do_not_translate_service_errors() -> None:
    found = [t for p in _modules(ROUTES) if p.name not in TRANSLATING_ROUTES for t in _translations(p)]
    assert not found, f"let the XrfError through (server/http/errors.py answers it): {found}"


def test_converted_routes_raise_kinds() -> None:
    found = [
        p.name
        for p in _modules(ROUTES)
        if p.name not in TRANSLATING_ROUTES and "HTTPException" in p.read_text(encoding="utf-8")
    ]
    assert not found, f"{found}: raise an xrflab.errors kind instead of HTTPException"


def test_the_lint_sees_a_translation(tmp_path: Path) -> None:
    planted = tmp_path / "planted.py"
    planted.write_text(
        "def f():\n    try:\n        g()\n    except SupervisorError as exc:\n"
        "        raise HTTPException(exc.status, str(exc)) from None\n"
    )
    assert _translations(planted) == ["planted.py:4 except SupervisorError"]
