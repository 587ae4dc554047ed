"""Request bodies are bounded before anything parses them (docs/developers/security.md).

A pure ASGI middleware, outside every route: a JSON body (login, commands, users, ...) is at most
``Settings.max_body_bytes``. A declared ``Content-Length`` over the limit is refused at once,
without reading a byte; otherwise the body is read here, counting as it comes (chunked bodies
declare no length), and refused the moment it passes the limit. What reaches the route is a
body already known to be small, so FastAPI's parser never holds more than the limit: before
this, an anonymous 300 MB login body grew the appliance from 291 MB to 1.5 GB.

The archive uploads stream to disk in their route with a limit of their own (archive.Limits);
here they only get a larger ceiling, checked on the declared length and counted while passing
through (never buffered).
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Awaitable, Callable, MutableMapping
from pathlib import Path
from typing import Any

from fastapi import Request

from ...errors import TooLarge

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

# The routes that take an archive (server/http/projects.py): they stream to a file themselves. And the
# editor's save (server/http/editor.py), whose file may be larger than a JSON body: it counts the body
# itself against its own limit (1 MB).
UPLOAD_ROUTES: tuple[tuple[str, re.Pattern[str]], ...] = (
    ("POST", re.compile(r"^/api/projects/?$")),
    ("PUT", re.compile(r"^/api/projects/[^/]+/source/?$")),
    ("PUT", re.compile(r"^/api/projects/[^/]+/files/.+$")),
)


class BodyTooLarge(Exception):
    """Raised into a streaming route when the body passes the upload ceiling."""


def _size(n: int) -> str:
    return f"{n >> 20} MB" if n >= 1 << 20 else f"{n >> 10} KB"


class BodyLimit:
    def __init__(self, app: ASGIApp, limit: int, upload_limit: int) -> None:
        self.app = app
        self.limit = limit
        self.upload_limit = upload_limit

    def _is_upload(self, scope: Scope) -> bool:
        method, path = scope.get("method", ""), scope.get("path", "")
        return any(method == m and rx.match(path) for m, rx in UPLOAD_ROUTES)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        upload = self._is_upload(scope)
        limit = self.upload_limit if upload else self.limit
        declared = _content_length(scope)
        if declared == -1:
            await _refuse(send, 400, "the Content-Length header is not a number")
            return
        if declared is not None and declared > limit:
            await _refuse(send, 413, f"the request body is {_size(declared)}; at most {_size(limit)} is accepted here")
            return
        if upload:
            await self._stream(scope, _counting(receive, limit), send, limit)
            return
        # Small bodies: read (bounded) before the route runs, then hand it over in one piece.
        chunks: list[bytes] = []
        total = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            body = message.get("body", b"")
            total += len(body)
            if total > limit:
                await _refuse(
                    send, 413, f"the request body is over {_size(limit)}; at most {_size(limit)} is accepted here"
                )
                return
            chunks.append(body)
            if not message.get("more_body", False):
                break
        await self.app(scope, _replay(b"".join(chunks), receive), send)

    async def _stream(self, scope: Scope, receive: Receive, send: Send, limit: int) -> None:
        started = False

        async def tracked(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, tracked)
        except BodyTooLarge:
            if not started:
                await _refuse(send, 413, f"the request body is over {_size(limit)}")


def _content_length(scope: Scope) -> int | None:
    """The declared length; None without one (chunked), -1 when it is not a number."""
    for name, value in scope.get("headers", ()):
        if name == b"content-length":
            try:
                n = int(value)
            except ValueError:
                return -1
            return n if n >= 0 else -1
    return None


def _replay(body: bytes, receive: Receive) -> Receive:
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()  # after the body: only http.disconnect is left to wait for

    return replay


def _counting(receive: Receive, limit: int) -> Receive:
    total = 0

    async def counted() -> Message:
        nonlocal total
        message = await receive()
        if message["type"] == "http.request":
            total += len(message.get("body", b""))
            if total > limit:
                raise BodyTooLarge(f"the request body is over {_size(limit)}")
        return message

    return counted


async def _refuse(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    # Connection: close, so the server does not wait for (or read) the rest of the body.
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


async def spool_to_file(
    request: Request, folder: Path, limit: int, *, prefix: str = "upload-", too_large: Any = None
) -> Path:
    """A route's streamed body (an archive upload) into a private temp file in `folder`, refused
    with 413 (`too_large` as its detail, else "over N MB") the moment it passes `limit` bytes;
    the partial file is removed on any failure. The caller owns the returned file."""
    fd, name = tempfile.mkstemp(dir=folder, prefix=prefix)
    total = 0
    try:
        with os.fdopen(fd, "wb") as f:
            async for chunk in request.stream():
                total += len(chunk)
                if total > limit:
                    raise TooLarge(f"over {limit >> 20} MB", detail=too_large)
                f.write(chunk)
    except BaseException:
        os.unlink(name)
        raise
    return Path(name)
