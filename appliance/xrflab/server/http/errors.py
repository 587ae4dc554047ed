"""The one handler of xrflab.errors.XrfError: every app (the appliance's and the room's) installs
it, so a service's error reaches the client with its status and message and no route translates."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from ...errors import XrfError

log = logging.getLogger(__name__)


async def _answer(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, XrfError)
    if exc.status >= 500:
        log.error("%s %s: %s", request.method, request.url.path, exc.message)
    return JSONResponse(exc.body(), status_code=exc.status, headers=exc.headers or None)


def install(app: FastAPI) -> None:
    app.add_exception_handler(XrfError, _answer)
