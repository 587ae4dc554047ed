"""The rerun viewer and the live stream, behind the login, on the appliance's own origin.

- ``GET /rerun/<file>``: the rerun web viewer (from the installed rerun-sdk, no CDN), copied once
  from rerun's internal file server (``logs.live.RerunViewer``, 127.0.0.1) into the data folder.
  Same origin as the dashboard, so the viewer fetches a finished run's ``.rrd`` from the API with
  the session cookie.
- ``GET /api/logs/rerun``: where the viewer and the live stream are for this request's host.
- ``POST /rerun.sdk_comms.v1alpha1.MessageProxyService/{ReadMessages,ReadTables}``: the live
  stream. rerun's viewer, given ``rerun+http://<host>:<port>/proxy``, calls these gRPC-web methods
  at the root of ``<host>:<port>`` (its URL parser accepts no path prefix), so they are answered
  here, at the appliance's root, by streaming the current run's rerun proxy (``logs.live.LiveProxy``,
  127.0.0.1 only) through: the login, the run's read permission (its owner or an educator, as for
  its log files; someone else's run answers as no stream at all) and a same-origin check apply to the live data as to everything else, and the
  Pi opened by its LAN address works like the Pi itself. Only the two read methods pass: nobody
  writes into a run's recording from a browser.

docs/logging/appliance.md describes the whole path.
"""

from __future__ import annotations

import asyncio
import os
import re
import urllib.parse
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, Response, StreamingResponse
from pydantic import BaseModel, Field
from starlette.background import BackgroundTask

from . import ownership
from .auth import Perm, requires, requires_grpc_web

router = APIRouter()

SERVICE = "rerun.sdk_comms.v1alpha1.MessageProxyService"
READ_METHODS = frozenset({"ReadMessages", "ReadTables"})
MAX_REQUEST_BYTES = 64 * 1024  # a read request is an (almost) empty protobuf message
MAX_LIVE_STREAMS = 16          # open live viewers at once (each is a replay of the run's buffer)
# Response headers of rerun's gRPC-web server worth passing on (the rest are hop-by-hop or CORS,
# which the same-origin viewer does not need).
_PASS_HEADERS = ("content-type", "grpc-status", "grpc-message", "grpc-encoding", "grpc-accept-encoding")
_ASSET = re.compile(r"^[A-Za-z0-9._-]*$")
_open_streams = 0
# The one answer for "nothing live" and for "live, but someone else's run" (ownership.py).
NO_LIVE_STREAM = ("no run you may watch has streamed since the appliance started "
                  "(a run's live data is its owner's and the educators')")

# gRPC status codes (grpc/doc/statuscodes.md) for answers the viewer can show.
NOT_FOUND, PERMISSION_DENIED, RESOURCE_EXHAUSTED, UNIMPLEMENTED, UNAVAILABLE = 5, 7, 8, 12, 14


class RerunInfo(BaseModel):
    available: bool
    error: str = ""
    viewer: str = Field(description="viewer page on this appliance (append ?url=...)")
    live_url: str = Field(description="rerun+http(s) URL of the live stream on this appliance's own origin "
                          "(the viewer reads it through the login); '' when there is nothing live to show")
    live_run: int | None = Field(description="run whose live stream the URL shows (the latest run that "
                                 "streamed), None before the first")
    live_recording: str = Field(description="its rerun recording id, 'run-<id>'")
    live_running: bool = Field(description="that run is still running")
    live_allowed: bool = Field(description="this user may watch it (its owner or an educator)")
    live_reason: str = Field(default="", description="why not, or why there is no live stream")
    live_viewers: int = Field(description="live viewers connected to the appliance right now")


def _origin(request: Request) -> str:
    """scheme://host:port of this request, with an explicit port (rerun's URL parser does not know
    the default port of a rerun+http(s) URL)."""
    scheme = request.url.scheme if request.url.scheme in ("http", "https") else "http"
    host = request.headers.get("host") or f"{request.url.hostname}:{request.url.port}"
    has_port = host.rsplit("]", 1)[-1].count(":") == 1
    if not has_port:
        host = f"{host}:{443 if scheme == 'https' else 80}"
    return f"{scheme}://{host}"


@router.get("/api/logs/rerun", response_model=RerunInfo, dependencies=[requires(Perm.WATCH)],
            summary="where the rerun viewer and the live stream are, for this request's host")
async def rerun_info(request: Request) -> dict[str, Any]:
    from ..logs.live import LiveProxy

    proxy = LiveProxy.current()
    sup = request.app.state.supervisor
    run = sup.current
    info: dict[str, Any] = {"available": True, "viewer": "/rerun/", "live_url": "", "live_run": None,
                            "live_recording": "", "live_running": False, "live_allowed": False,
                            "live_viewers": _open_streams}
    # Someone else's stream answers as no stream at all (ownership.py): not even its run id.
    if proxy is None or not ownership.may_see(ownership.user_of(request), proxy.owner):
        info["live_reason"] = NO_LIVE_STREAM
        return info
    info.update(live_run=proxy.run_id, live_recording=f"run-{proxy.run_id}",
                live_running=bool(run is not None and run.row.id == proxy.run_id and run.alive
                                  and not run.ended.is_set()))
    scheme, hostport = _origin(request).split("://", 1)
    info.update(live_allowed=True, live_url=f"rerun+{scheme}://{hostport}/proxy")
    return info


@router.get("/rerun/{asset:path}", dependencies=[requires(Perm.WATCH)], include_in_schema=False)
async def rerun_viewer(asset: str, request: Request) -> Response:
    """The rerun web viewer's files, fetched once from rerun's internal server and kept on disk
    (keyed by the rerun version): the 40 MB wasm is served by us, with our caching and auth."""
    import httpx
    import rerun

    from ..logs.live import RerunViewer

    asset = asset or "index.html"
    if not _ASSET.match(asset) or asset.startswith("."):
        raise HTTPException(404, "no such viewer file")
    settings = request.app.state.settings
    cache = Path(settings.data_dir) / "rerun-viewer" / rerun.__version__
    path = cache / asset
    if not path.is_file():
        try:
            viewer = await asyncio.to_thread(RerunViewer.get)
        except OSError as exc:
            raise HTTPException(503, f"the rerun viewer is not available: {exc}") from None
        async with httpx.AsyncClient(timeout=60) as client:
            r = await client.get(f"http://127.0.0.1:{viewer.web_port}/{asset}")
        if r.status_code != 200:
            raise HTTPException(404, f"the rerun viewer has no {asset}")
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{asset}.{os.getpid()}.part")
        tmp.write_bytes(r.content)
        os.replace(tmp, path)
    media = {".html": "text/html", ".js": "text/javascript", ".wasm": "application/wasm",
             ".ico": "image/x-icon", ".png": "image/png", ".css": "text/css"}.get(path.suffix)
    cache_control = "no-cache" if asset == "index.html" else "public, max-age=86400"
    return FileResponse(path, media_type=media, headers={"Cache-Control": cache_control})


# ---- the live stream ------------------------------------------------------------------------


def grpc_error(http_status: int, code: int, message: str) -> Response:
    """A trailers-only gRPC-web answer (status in the headers) that also reads as plain HTTP."""
    return Response(status_code=http_status, media_type="application/grpc-web+proto",
                    headers={"grpc-status": str(code), "grpc-message": urllib.parse.quote(message, safe=" ,.:'()-")})


async def _read_request(request: Request) -> bytes | None:
    """The request body, or None when it is larger than a read request can be."""
    declared = request.headers.get("content-length")
    if declared is not None and (not declared.isdigit() or int(declared) > MAX_REQUEST_BYTES):
        return None
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_REQUEST_BYTES:
            return None
    return bytes(body)


@router.post(f"/{SERVICE}/{{method}}", dependencies=[requires_grpc_web(Perm.WATCH)], include_in_schema=False)
async def live_stream(method: str, request: Request) -> Response:
    global _open_streams
    import httpx

    from ..logs.live import LiveProxy

    if method not in READ_METHODS:
        return grpc_error(403, PERMISSION_DENIED, f"{method}: the live stream is read-only here")
    proxy = LiveProxy.current()
    if proxy is None or not ownership.may_see(ownership.user_of(request), proxy.owner):
        return grpc_error(404, NOT_FOUND, NO_LIVE_STREAM)  # someone else's: as if there were none
    body = await _read_request(request)
    if body is None:
        return grpc_error(413, RESOURCE_EXHAUSTED, f"a read request is at most {MAX_REQUEST_BYTES} bytes")
    if _open_streams >= MAX_LIVE_STREAMS:
        return grpc_error(503, RESOURCE_EXHAUSTED, f"{MAX_LIVE_STREAMS} live viewers are open already; close one")

    headers = {"content-type": request.headers.get("content-type", "application/grpc-web+proto"), "x-grpc-web": "1"}
    if "grpc-timeout" in request.headers:
        headers["grpc-timeout"] = request.headers["grpc-timeout"]
    # No read timeout: a live stream is quiet between runs and that is not an error.
    client = httpx.AsyncClient(timeout=httpx.Timeout(10.0, read=None))
    try:
        upstream = await client.send(client.build_request("POST", f"{proxy.read_url}/{SERVICE}/{method}",
                                                          content=body, headers=headers), stream=True)
    except httpx.HTTPError as exc:
        await client.aclose()
        return grpc_error(502, UNAVAILABLE, f"the live stream of run {proxy.run_id} does not answer: {exc}")
    _open_streams += 1
    closed = False

    async def close() -> None:
        nonlocal closed
        global _open_streams
        if not closed:
            closed = True
            _open_streams -= 1
            await upstream.aclose()
            await client.aclose()

    async def relay() -> AsyncIterator[bytes]:
        # Runs until the run's proxy ends the stream (the next run replaced it) or the browser
        # goes away (Starlette cancels us): either way both connections are closed here.
        try:
            async for chunk in upstream.aiter_raw():
                yield chunk
        except httpx.HTTPError:
            pass  # the run's proxy stopped mid-stream: end ours; the viewer reports the closed stream
        finally:
            await close()

    out = {k: v for k, v in upstream.headers.items() if k.lower() in _PASS_HEADERS}
    out["cache-control"] = "no-store"
    out["x-accel-buffering"] = "no"  # a reverse proxy in front must not hold the stream back
    # The background close covers a response cancelled before its first chunk.
    return StreamingResponse(relay(), status_code=upstream.status_code, headers=out, background=BackgroundTask(close))
