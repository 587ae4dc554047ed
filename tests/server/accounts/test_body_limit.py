"""The body-limit middleware in-process (server/security/body_limit.py), driven as an ASGI server
drives it: a declared length over the limit is refused unread, a chunked body the moment it passes
the limit, a small body reaches the route whole, uploads get their ceiling and are never buffered.
test_bounded_input.py sends the same through a real appliance."""

from __future__ import annotations

import asyncio
import json
from typing import Any

from xrflab.server.security.body_limit import BodyLimit, BodyTooLarge

LIMIT = 1000
UPLOAD_LIMIT = 5000


class Exchange:
    """One request through BodyLimit around a route that reads its whole body."""

    def __init__(self, method: str, path: str, chunks: list[bytes], length: int | str | None = None) -> None:
        self.pending = [
            {"type": "http.request", "body": c, "more_body": i < len(chunks) - 1} for i, c in enumerate(chunks)
        ]
        self.read = 0  # messages the middleware (or the route) took
        self.sent: list[dict[str, Any]] = []
        self.route_body: bytes | None = None
        self.route_chunks = 0
        headers = [] if length is None else [(b"content-length", str(length).encode())]
        self.scope = {"type": "http", "method": method, "path": path, "headers": headers}

    async def receive(self) -> dict[str, Any]:
        self.read += 1
        return self.pending.pop(0) if self.pending else {"type": "http.disconnect"}

    async def send(self, message: dict[str, Any]) -> None:
        self.sent.append(message)

    async def route(self, scope: Any, receive: Any, send: Any) -> None:
        body = b""
        while True:
            m = await receive()
            self.route_chunks += 1
            body += m.get("body", b"")
            if not m.get("more_body"):
                break
        self.route_body = body
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    def run(self) -> Exchange:
        asyncio.run(BodyLimit(self.route, LIMIT, UPLOAD_LIMIT)(self.scope, self.receive, self.send))
        return self

    @property
    def status(self) -> int:
        return self.sent[0]["status"]

    @property
    def detail(self) -> str:
        return json.loads(self.sent[1]["body"])["detail"]


def test_a_small_body_reaches_the_route_whole_in_one_piece() -> None:
    ex = Exchange("POST", "/api/auth/login", [b"a" * 400, b"b" * 400], length=800).run()
    assert ex.status == 200 and ex.route_body == b"a" * 400 + b"b" * 400
    assert ex.route_chunks == 1  # read here, handed over at once


def test_a_declared_length_over_the_limit_is_refused_before_reading() -> None:
    ex = Exchange("POST", "/api/auth/login", [b"x" * 10], length=LIMIT + 1).run()
    assert ex.status == 413 and ex.read == 0 and ex.route_body is None
    assert ex.detail.startswith("the request body is")
    assert (b"connection", b"close") in ex.sent[0]["headers"]


def test_a_chunked_body_is_refused_the_moment_it_passes_the_limit() -> None:
    chunks = [b"x" * 600, b"x" * 600, b"x" * 600, b"x" * 600]
    ex = Exchange("POST", "/api/users", chunks).run()
    assert ex.status == 413 and ex.route_body is None
    assert ex.read == 2  # the second chunk passed the limit; the rest was never read


def test_a_length_that_is_not_a_number_is_a_bad_request() -> None:
    for bad in ("12abc", "-5"):
        ex = Exchange("POST", "/api/users", [b"{}"], length=bad).run()
        assert ex.status == 400 and "not a number" in ex.detail, bad


def test_uploads_get_their_own_ceiling_and_stream_through() -> None:
    body = [b"z" * 1000] * 4  # 4000: over the JSON limit, under the upload ceiling
    ex = Exchange("POST", "/api/projects", body).run()
    assert ex.status == 200 and ex.route_body == b"".join(body)
    assert ex.route_chunks == 4  # passed through as it came, never buffered here
    # and the same route past its ceiling: the route's read raises, the client gets 413
    ex = Exchange("PUT", "/api/projects/7/source", [b"z" * 3000, b"z" * 3000]).run()
    assert ex.status == 413 and ex.route_body is None
    # declared over the ceiling: refused unread
    ex = Exchange("PUT", "/api/projects/7/files/src/main.cpp", [b""], length=UPLOAD_LIMIT + 1).run()
    assert ex.status == 413 and ex.read == 0


def test_not_http_passes_untouched() -> None:
    seen: list[str] = []

    async def app(scope: Any, receive: Any, send: Any) -> None:
        seen.append(scope["type"])

    asyncio.run(BodyLimit(app, LIMIT, UPLOAD_LIMIT)({"type": "websocket"}, None, None))  # type: ignore[arg-type]
    assert seen == ["websocket"]
    assert issubclass(BodyTooLarge, Exception)
