"""What a browser gets for paths that are not the API: the tab's icon, and the dashboard for a page
path typed or bookmarked without its ``#``.

The dashboard's pages are fragments of ``/`` (``/#users``); ``/users`` used to answer the API's
``{"detail":"Not Found"}`` to a person. A browser's navigation (``Sec-Fetch-Mode: navigate``, or
an ``Accept`` that prefers HTML) to a one-segment path outside the API is redirected to that
fragment (the dashboard shows its Bench page for a name it does not know); deeper unknown paths
get a short HTML page with a link home. Programs (no HTML in ``Accept``) and everything under
``/api/`` keep the JSON 404, so the API's answers do not depend on who asks.

The icon is drawn here at import (a 32x32 ICO, the accent blue of style.css with a white cross
of two bars): nothing a student's browser loads comes from outside, and the repository keeps no
binary for it.
"""

from __future__ import annotations

import html
import re
import struct

from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response

# Paths that belong to programs: never redirected, whatever the Accept header says.
_MACHINE_PREFIXES = ("/api/", "/api", "/static/", "/ws", "/rerun", "/viser", "/room/")
_PAGE_RE = re.compile(r"^/([a-z][a-z0-9-]{0,40})/?$")

_SIZE = 32
_ACCENT_BGRA = (0xEB, 0x6F, 0x1F, 0xFF)  # #1f6feb, style.css's --accent
_WHITE_BGRA = (0xFF, 0xFF, 0xFF, 0xFF)
_CLEAR_BGRA = (0, 0, 0, 0)


def _pixel(x: int, y: int) -> tuple[int, int, int, int]:
    # A rounded square (corners cut) with a white "X" of two diagonal bars, 4 px wide.
    corner = 4
    dx, dy = min(x, _SIZE - 1 - x), min(y, _SIZE - 1 - y)
    if dx + dy < corner:
        return _CLEAR_BGRA
    inner = 7 <= x <= 24 and 7 <= y <= 24
    if inner and (abs(x - y) <= 2 or abs(x + y - (_SIZE - 1)) <= 2):
        return _WHITE_BGRA
    return _ACCENT_BGRA


def _make_icon() -> bytes:
    """One 32-bit image in an ICO container: a BITMAPINFOHEADER (height doubled, as ICO wants:
    colour rows then the 1-bit AND mask), rows bottom-up in BGRA, an all-zero mask (alpha rules)."""
    rows = b"".join(bytes(c for x in range(_SIZE) for c in _pixel(x, y)) for y in reversed(range(_SIZE)))
    mask = bytes(((_SIZE + 31) // 32) * 4 * _SIZE)
    info = struct.pack("<IiiHHIIiiII", 40, _SIZE, _SIZE * 2, 1, 32, 0, len(rows) + len(mask), 0, 0, 0, 0)
    image = info + rows + mask
    header = struct.pack("<HHH", 0, 1, 1)
    entry = struct.pack("<BBBBHHII", _SIZE, _SIZE, 0, 0, 1, 32, len(image), 6 + 16)
    return header + entry + image


FAVICON = _make_icon()


def favicon_response() -> Response:
    # A day's caching: it never changes within a release, and every page load would ask again.
    return Response(FAVICON, media_type="image/x-icon", headers={"Cache-Control": "public, max-age=86400"})


def _is_navigation(request: Request) -> bool:
    if request.method not in ("GET", "HEAD"):
        return False
    if request.headers.get("sec-fetch-mode") == "navigate":
        return True
    accept = request.headers.get("accept", "")
    return "text/html" in accept


_NOT_FOUND_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>XRF Lab: no such page</title>
<link rel="icon" href="/favicon.ico"></head>
<body style="font-family: system-ui, sans-serif; margin: 3rem;">
<h1>No page at {path}</h1>
<p>The dashboard's pages are at <a href="/">{host}/</a> (Bench, Projects, Runs, …).</p>
</body></html>
"""


async def _not_found(request: Request, exc: Exception) -> Response:
    """Starlette's 404 for a path no route matches (registered by status code: services' own
    NotFound is an XrfError, answered by http/errors.py, never here)."""
    path = request.url.path
    if _is_navigation(request) and not path.startswith(_MACHINE_PREFIXES):
        m = _PAGE_RE.match(path)
        if m:
            return RedirectResponse(f"/#{m[1]}", status_code=303)
        page = _NOT_FOUND_PAGE.format(path=html.escape(path), host=html.escape(request.url.netloc))
        return HTMLResponse(page, status_code=404)
    # Everything else as FastAPI answers it by default.
    detail = getattr(exc, "detail", "Not Found")
    return JSONResponse({"detail": detail}, status_code=404, headers=getattr(exc, "headers", None))


def install(app: FastAPI) -> None:
    """The page fallback for a browser's 404 (the icon's route is app.py's: it needs the
    permission dependency every route carries)."""
    app.add_exception_handler(404, _not_found)
