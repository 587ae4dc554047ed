"""The appliance's one error type: what a request could not do, said to whoever asked.

Services (runs, projects, accounts, the lease, self-checks, logs) raise ``XrfError`` or one of its
kinds below; they never build HTTP responses. One exception handler (server/http/errors.py) turns
it into the answer: the HTTP status, ``{"detail": message}`` (FastAPI's own shape, so clients and
tests read every error the same way), or ``{"detail": detail}`` when the error carries a typed
detail (e.g. the field errors of a profile), and any headers it names (``Retry-After``).

This module imports nothing of the package: every layer, down to the domain, may raise it.
"""

from __future__ import annotations

from typing import Any


class XrfError(Exception):
    """A request the appliance cannot honour. `status`: the HTTP status it maps to; `detail`:
    a JSON-able value sent instead of the message (the message stays the log's and str()'s)."""

    status = 400

    def __init__(
        self,
        message: str,
        status: int | None = None,
        *,
        detail: Any = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        if status is not None:
            self.status = status
        self.detail = detail
        self.headers = headers or {}

    def body(self) -> dict[str, Any]:
        return {"detail": self.detail if self.detail is not None else self.message}


class Invalid(XrfError):
    """The request is understood but its content is wrong (a field, a name, an archive)."""

    status = 422


class Denied(XrfError):
    """The caller may not do this (their role, the lease, a CSRF header)."""

    status = 403


class NotFound(XrfError):
    """No such thing, or someone else's: the two look the same to the caller."""

    status = 404


class Conflict(XrfError):
    """Not now: the bench is busy, a run is active, a version moved on."""

    status = 409


class TooLarge(XrfError):
    status = 413


class Busy(XrfError):
    """Too many requests; `headers` may carry Retry-After."""

    status = 429


class Unavailable(XrfError):
    """Something the request needs is not there (a tool, a device, the room)."""

    status = 503
