"""The 3D view's viser server, behind the login: a reverse proxy at ``/viser/``.

viser (xrflab.viz.scene) listens on 127.0.0.1 only (an internal port); browsers reach it through
the appliance, with the same session and permission (``Perm.WATCH``) as the rest of the dashboard:

- ``GET /viser/<path>``: viser's client files, streamed from its internal HTTP server (httpx);
  its index.html with our tab script added (``_index``: the scene opens in a tab of its own).
- WebSocket ``/viser`` (and ``/viser/<path>``): viser's client opens its WebSocket at the page's
  own URL without the query and the trailing slash (``getDefaultServerFromUrl`` in viser's
  ``client/src/App.tsx``), so a page at ``/viser/`` connects to ``ws(s)://<host>/viser``. The
  handshake needs a session and, with the cookie, a same-origin ``Origin`` (``auth.check``, as for
  ``/ws``); the subprotocol (``viser-v<version>``, viser's version check) is passed through. The
  session is checked again every few seconds: a logout or a disabled account closes the scene.

The scene's own panel is display only (scene.py ``_build_gui``): changes go through /api/viz.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

from fastapi import APIRouter, Request, WebSocket
from fastapi.responses import RedirectResponse, Response, StreamingResponse
from starlette.background import BackgroundTask
from starlette.websockets import WebSocketDisconnect

from ... import loopback
from ...errors import Unavailable, XrfError
from ...logs.rerun_servers import LIB_SCRIPT, TAB_SCRIPT
from ..security.auth import Perm, may, requires

router = APIRouter(include_in_schema=False)

# Response headers of viser's server worth passing on (the rest are hop-by-hop or ours).
_PASS_HEADERS = ("content-type", "content-length", "content-encoding", "cache-control", "last-modified", "etag")
SESSION_RECHECK_S = 5.0
MAX_MESSAGE = 50 * 1024 * 1024  # viser's own limit
# Added to viser's page: the frontend's shared helpers, then the viewer tabs' Esc-stops script
# (the same ones rerun's page gets).
TAB_SCRIPTS = (LIB_SCRIPT, TAB_SCRIPT)


async def _viser_port(app: Any) -> int | None:
    """viser's port; the first request starts it (viz/scene.py ensure_server: it is not started
    with the appliance)."""
    viz = getattr(app.state, "viz", None)
    if viz is None:
        return None
    if viz.server is None:
        return await asyncio.to_thread(viz.ensure_server)
    return int(viz.port) if viz.port else None


@router.get("/viser", dependencies=[requires(Perm.WATCH)])
async def viser_root() -> RedirectResponse:
    return RedirectResponse("/viser/", status_code=307)


@router.get("/viser/{path:path}", dependencies=[requires(Perm.WATCH)])
async def viser_http(path: str, request: Request) -> Response:
    import httpx

    port = await _viser_port(request.app)
    if port is None:
        raise Unavailable("the 3D view is not running")
    url = f"http://127.0.0.1:{port}/{path}"
    if path in ("", "index.html"):
        return await _index(url, request)
    headers = {"accept-encoding": request.headers.get("accept-encoding", "identity")}
    client = loopback.async_client(timeout=httpx.Timeout(30.0))
    try:
        upstream = await client.send(
            client.build_request("GET", url, params=request.query_params, headers=headers), stream=True
        )
    except httpx.HTTPError as exc:
        await client.aclose()
        raise XrfError(f"the 3D view does not answer: {loopback.why_failed(exc)}", 502) from None  # bad gateway

    async def close() -> None:
        await upstream.aclose()
        await client.aclose()

    out = {k: v for k, v in upstream.headers.items() if k.lower() in _PASS_HEADERS}
    out.setdefault("cache-control", "no-cache")
    # aiter_raw: the bytes as viser sent them (gzip stays gzip; content-length stays right).
    return StreamingResponse(
        upstream.aiter_raw(), status_code=upstream.status_code, headers=out, background=BackgroundTask(close)
    )


async def _index(url: str, request: Request) -> Response:
    """viser's page with ours added at the end of its head (``TAB_SCRIPTS``): the scene opens in a
    tab of its own (frontend/pages/view3d.js, issue 31 bug 7), where the dashboard's key handler
    is not, so that script keeps "Esc stops the run from anywhere" (issue 19) as in rerun's tab."""
    import httpx

    async with loopback.async_client(timeout=httpx.Timeout(30.0)) as client:
        try:
            r = await client.get(url, params=request.query_params, headers={"accept-encoding": "identity"})
        except httpx.HTTPError as exc:
            raise XrfError(f"the 3D view does not answer: {loopback.why_failed(exc)}", 502) from None  # bad gateway
    text = r.text
    tags = "".join(f'<script src="{src}"></script>\n' for src in TAB_SCRIPTS)
    text = text.replace("</head>", tags + "</head>", 1) if "</head>" in text else tags + text
    return Response(text, status_code=r.status_code, media_type="text/html", headers={"cache-control": "no-cache"})


@router.websocket("/viser", dependencies=[requires(Perm.WATCH)])
async def viser_ws(ws: WebSocket) -> None:
    await _proxy_ws(ws)


@router.websocket("/viser/{path:path}", dependencies=[requires(Perm.WATCH)])
async def viser_ws_path(ws: WebSocket, path: str) -> None:
    await _proxy_ws(ws)


async def _proxy_ws(ws: WebSocket) -> None:
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed
    from websockets.typing import Subprotocol

    port = await _viser_port(ws.app)
    if port is None:
        await ws.close(code=1011, reason="the 3D view is not running")
        return
    offered = [Subprotocol(p) for p in ws.scope.get("subprotocols", [])]
    try:
        upstream = await connect(
            f"ws://127.0.0.1:{port}/",
            subprotocols=offered or None,
            max_size=MAX_MESSAGE,
            compression=None,
            open_timeout=10,
            origin=None,
        )
    except Exception:
        await ws.close(code=1011, reason="the 3D view does not answer")
        return
    viz = ws.app.state.viz
    async with upstream:
        await ws.accept(subprotocol=upstream.subprotocol)
        # Browsers reach viser only through here: the scene updates while one is connected
        # (viz/scene.py watched(); issue 30 item 4).
        viz.viewer_joined()

        async def browser_to_viser() -> None:
            while True:
                message = await ws.receive()
                if message["type"] == "websocket.disconnect":
                    return
                data = message.get("bytes")
                await upstream.send(data if data is not None else message.get("text") or "")

        async def viser_to_browser() -> None:
            async for data in upstream:
                if isinstance(data, bytes):
                    await ws.send_bytes(data)
                else:
                    await ws.send_text(data)

        async def session_alive() -> None:
            security = ws.app.state.security
            while True:
                await asyncio.sleep(SESSION_RECHECK_S)
                ws.scope.pop("xrf_auth", None)
                user = security.resolve(ws)[0]
                if user is None or user.must_change or not may(user, Perm.WATCH):
                    return

        tasks = [asyncio.create_task(c) for c in (browser_to_viser(), viser_to_browser(), session_alive())]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            viz.viewer_left()
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        ended = tasks[2] in done
        with contextlib.suppress(Exception, WebSocketDisconnect, ConnectionClosed):
            await ws.close(code=1008 if ended else 1000, reason="your session ended" if ended else "")
