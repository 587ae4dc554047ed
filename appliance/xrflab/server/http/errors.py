"""The one handler of xrflab.errors.XrfError: every app (the appliance's and the room's) installs
it, so a service's error reaches the client with its status and message and no route translates."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from ...errors import XrfError

log = logging.getLogger(__name__)


def _text(value: Any) -> Any:
    """A message may quote a file name (a log's path): a lone surrogate from the file system would
    make the JSON answer fail to encode, so it is written as a backslash escape instead."""
    if isinstance(value, str):
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    return value


async def _answer(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, XrfError)
    if exc.status >= 500:
        log.error("%s %s: %s", request.method, request.url.path, _text(str(exc)))
    body = exc.body()
    body["detail"] = _text(body["detail"])
    return JSONResponse(body, status_code=exc.status, headers=exc.headers or None)


def install(app: FastAPI) -> None:
    app.add_exception_handler(XrfError, _answer)
