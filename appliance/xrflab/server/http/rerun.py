"""The rerun viewer and the live stream, behind the login, on the appliance's own origin.

- ``GET /rerun/<file>``: the rerun web viewer (from the installed rerun-sdk, no CDN), copied once
  from rerun's internal file server (``logs.rerun_servers.RerunViewer``, 127.0.0.1) into the data
  folder, by a child process that stops that server when the copy is made (``logs/rerun_files.py``).
  Same origin as the dashboard, so the viewer fetches a finished run's ``.rrd`` from the API with
  the session cookie. **Offline** (issue 19): as shipped, the viewer fetches Google Fonts, sends
  analytics to tel.rerun.io, asks GitHub for the latest release and app.rerun.io for its examples,
  from every student's browser. Its web build has no switch for any of these, so the copy is
  neutralised (``finish_viewer``, ``rerun_files.neutralise_wasm_file``): the font links leave index.html, and the absolute URLs in the
  wasm are overwritten, byte for byte the same length, by paths under ``/rerun/offline/`` on the
  appliance, which answers 404 at once. A Content-Security-Policy (``connect-src 'self'`` and
  friends) on every viewer file stops whatever a later rerun version adds before it leaves the
  browser. **Compressed**: each file is kept gzipped beside the original (the 43 MB wasm is 14 MB)
  and served with ``Content-Encoding: gzip`` to browsers that accept it. **Ours**: index.html
  also loads ``/static/rerun-tab.js`` (``TAB_SCRIPT``, after ``/static/lib.js``): the Runs page opens the viewer in a tab of
  its own, where that script makes Esc stop the run (issue 19).
- ``GET /api/logs/rerun``: where the viewer and the live stream are for this request's host.
- ``GET /api/logs/rerun/warmup.rrd``: a small recording of our own that the live viewer draws before
  the run's data and then closes (``logs.rerun_warmup``; frontend/rerun-tab.js): its render
  pipelines are built then, not in the frame with the run's first samples (issue 31 bug 6).
- ``POST /rerun.sdk_comms.v1alpha1.MessageProxyService/{ReadMessages,ReadTables}``: the live
  stream. rerun's viewer, given ``rerun+http://<host>:<port>/proxy``, calls these gRPC-web methods
  at the root of ``<host>:<port>`` (its URL parser accepts no path prefix), so they are answered
  here, at the appliance's root, by streaming the current run's rerun proxy (``logs.rerun_servers.LiveProxy``,
  127.0.0.1 only) through: the login, the run's read permission (its owner or an educator, as for
  its log files; someone else's run answers as no stream at all) and a same-origin check apply to the live data as to everything else, and the
  Pi opened by its LAN address works like the Pi itself. Only the two read methods pass: nobody
  writes into a run's recording from a browser.

docs/logging/appliance.md describes the whole path.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import shutil
import threading
import urllib.parse
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, Response, StreamingResponse
from pydantic import BaseModel, Field
from starlette.background import BackgroundTask

from ... import loopback
from ...errors import NotFound, Unavailable
from ...logs.convert_child import heavy_turn
from ...logs.rerun_files import VIEWER_FILES
from ...logs.rerun_servers import LIB_SCRIPT, TAB_SCRIPT
from ..security import ownership
from ..security.auth import Perm, requires, requires_grpc_web

router = APIRouter()

SERVICE = "rerun.sdk_comms.v1alpha1.MessageProxyService"
READ_METHODS = frozenset({"ReadMessages", "ReadTables"})
MAX_REQUEST_BYTES = 64 * 1024  # a read request is an (almost) empty protobuf message
MAX_LIVE_STREAMS = 16  # open live viewers at once (each is a replay of the run's buffer)
# Response headers of rerun's gRPC-web server worth passing on (the rest are hop-by-hop or CORS,
# which the same-origin viewer does not need).
_PASS_HEADERS = ("content-type", "grpc-status", "grpc-message", "grpc-encoding", "grpc-accept-encoding")
_open_streams = 0
# The one answer for "nothing live" and for "live, but someone else's run" (server/security/ownership.py).
NO_LIVE_STREAM = (
    "no run you may watch has streamed since the appliance started "
    "(a run's live data is its owner's and the educators')"
)

# gRPC status codes (grpc/doc/statuscodes.md) for answers the viewer can show.
NOT_FOUND, PERMISSION_DENIED, RESOURCE_EXHAUSTED, UNIMPLEMENTED, UNAVAILABLE = 5, 7, 8, 12, 14


class RerunInfo(BaseModel):
    available: bool
    error: str = ""
    viewer: str = Field(description="viewer page on this appliance (append ?url=...)")
    live_url: str = Field(
        description="rerun+http(s) URL of the live stream on this appliance's own origin "
        "(the viewer reads it through the login); '' when there is nothing live to show"
    )
    live_run: int | None = Field(
        description="run whose live stream the URL shows (the latest run that streamed), None before the first"
    )
    live_recording: str = Field(description="its rerun recording id, 'run-<id>'")
    live_running: bool = Field(description="that run is still running")
    live_allowed: bool = Field(description="this user may watch it (its owner or an educator)")
    live_reason: str = Field(default="", description="why not, or why there is no live stream")
    live_viewers: int = Field(description="live viewers connected to the appliance right now")
    live_span_s: float = Field(description="each plot of the live view shows its last this many seconds")
    live_points_per_s: float = Field(
        description="the live view's display rate: points per second per logged variable (each interval's "
        "min and max); every sample is in the run's log"
    )


def _origin(request: Request) -> str:
    """scheme://host:port of this request, with an explicit port (rerun's URL parser does not know
    the default port of a rerun+http(s) URL)."""
    scheme = request.url.scheme if request.url.scheme in ("http", "https") else "http"
    host = request.headers.get("host") or f"{request.url.hostname}:{request.url.port}"
    has_port = host.rsplit("]", 1)[-1].count(":") == 1
    if not has_port:
        host = f"{host}:{443 if scheme == 'https' else 80}"
    return f"{scheme}://{host}"


@router.get(
    "/api/logs/rerun",
    response_model=RerunInfo,
    dependencies=[requires(Perm.WATCH)],
    summary="where the rerun viewer and the live stream are, for this request's host",
)
async def rerun_info(request: Request) -> dict[str, Any]:
    from ...logs.rerun_live import LIVE_HZ, LIVE_SPAN_S
    from ...logs.rerun_servers import LiveProxy

    proxy = LiveProxy.current()
    sup = request.app.state.supervisor
    run = sup.current
    info: dict[str, Any] = {
        "available": True,
        "viewer": "/rerun/",
        "live_url": "",
        "live_run": None,
        "live_recording": "",
        "live_running": False,
        "live_allowed": False,
        "live_viewers": _open_streams,
        "live_span_s": LIVE_SPAN_S,
        "live_points_per_s": LIVE_HZ,
    }
    # Someone else's stream answers as no stream at all (server/security/ownership.py): not even its run id.
    if proxy is None or not ownership.may_see(ownership.user_of(request), proxy.owner):
        info["live_reason"] = NO_LIVE_STREAM
        return info
    info.update(
        live_run=proxy.run_id,
        live_recording=f"run-{proxy.run_id}",
        live_running=bool(run is not None and run.row.id == proxy.run_id and run.alive and not run.ended.is_set()),
    )
    scheme, hostport = _origin(request).split("://", 1)
    info.update(live_allowed=True, live_url=f"rerun+{scheme}://{hostport}/proxy")
    return info


@router.get("/api/logs/rerun/warmup.rrd", dependencies=[requires(Perm.WATCH)], include_in_schema=False)
async def rerun_warmup() -> Response:
    """The live viewer's warm-up recording (logs/rerun_warmup.py): drawn by the viewer before the
    run's data, then closed by the tab (frontend/rerun-tab.js), so that the frame with the run's
    first samples does not also build the viewer's render pipelines (issue 31 bug 6)."""
    from ...logs.rerun_warmup import warmup_rrd

    return Response(
        warmup_rrd(),
        media_type="application/octet-stream",
        headers={"Cache-Control": "private, max-age=86400", "X-Content-Type-Options": "nosniff"},
    )


# The viewer's files (rerun_files.VIEWER_FILES), prepared once per rerun version (_viewer_cache);
# the wasm's URLs pointed at OFFLINE_PREFIX (rerun_files.WASM_URLS).
# index.html: Google Fonts (the loading text's font; the viewer draws with its own fonts) and the
# script app.rerun.io loads for its own site.
_FONT_LINKS = re.compile(r"<link[^>]*(fonts\.googleapis\.com|fonts\.gstatic\.com)[^>]*>", re.S)
_SITE_SCRIPT = re.compile(r'if \(window\.location\.hostname == "app\.rerun\.io"\) \{.*?\n      \}\n', re.S)
# Every viewer file carries it: nothing but this origin (the wasm compiled in the page, workers
# from blobs, inline scripts and styles of rerun's index.html).
VIEWER_CSP = (
    "default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; "
    "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
    "connect-src 'self'; worker-src 'self' blob:; media-src 'self' blob:; frame-ancestors 'self'; "
    "form-action 'none'; base-uri 'self'"
)
# Ours (logs.rerun_servers TAB_SCRIPT after LIB_SCRIPT), served from the dashboard's static files
# (same origin: the CSP's script-src 'self' allows it).
# Part of the prepared copy's folder name: a change to what the preparation does to rerun's files
# (here: LIB_SCRIPT and TAB_SCRIPT added to index.html) makes appliances prepare their copy again.
PREPARED_AS = "offline-tab-lib-wasm-warmup"
_MEDIA = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript",
    ".wasm": "application/wasm",
    ".ico": "image/x-icon",
    ".png": "image/png",
    ".css": "text/css",
}
_prepare_lock = asyncio.Lock()


# index.html's loader reads the wasm through a stream of its own (for a percentage) and deletes
# WebAssembly.instantiateStreaming: the 43 MB were compiled from an array buffer after the whole
# download, at every opening (a compiled module is cached by the browser only when compiled from
# the fetched response). Our tab script starts WebAssembly.compileStreaming on the wasm's fetch
# while the page is still loading (frontend/rerun-tab.js ``wasm``), and the loader takes that
# module when it is there (issue 31 bug 6: the live viewer's start).
_LOADER_CALL = "        wasm_with_progress();\n"
_LOADER_OURS = (
    "        if (window.xrfRerunTab && xrfRerunTab.wasm) {\n"
    "          wasm_bindgen({ module_or_path: xrfRerunTab.wasm })\n"
    "            .then(() => (clearTimeout(timeoutId), on_wasm_loaded()))\n"
    "            .catch(on_wasm_error);\n"
    "        } else wasm_with_progress();\n"
)


# index.html hands the started app's handle to our tab script at once (frontend/rerun-tab.js
# ``appStarted``: the live viewer's warm-up, issue 31 bug 6), not only as window._handle.
_APP_STARTED = "        window._handle = handle;\n"
_APP_STARTED_OURS = _APP_STARTED + (
    "        if (window.xrfRerunTab && xrfRerunTab.appStarted) xrfRerunTab.appStarted(handle);\n"
)


def neutralise_index(text: str) -> str:
    text = _FONT_LINKS.sub("", text)
    if _LOADER_CALL not in text:  # a newer rerun: its own loader, as shipped
        logging.getLogger("xrflab.rerun").warning("rerun viewer: index.html's wasm loader not found; left as it is")
    text = text.replace(_LOADER_CALL, _LOADER_OURS, 1)
    if _APP_STARTED not in text:  # a newer rerun: no warm-up (the live view works without it)
        logging.getLogger("xrflab.rerun").warning("rerun viewer: index.html's app start not found; no warm-up")
    text = text.replace(_APP_STARTED, _APP_STARTED_OURS, 1)
    text = _SITE_SCRIPT.sub("", text)
    # No bug-report links to GitHub in the viewer's error page: a student reports to the educator.
    text = text.replace("https://github.com/rerun-io/rerun/issues/new/", "#")
    # Our script, at the end of the head: Esc stops the run from the viewer's
    # tab (the dashboard's key handler is in another tab) and a live viewer follows the next run.
    tag = f'<script src="{LIB_SCRIPT}"></script>\n<script src="{TAB_SCRIPT}"></script>\n'
    return text.replace("</head>", tag + "</head>", 1) if "</head>" in text else tag + text


def finish_viewer(folder: Path, cache: Path) -> None:
    """The copy made by the preparing child (logs/rerun_files.py: every file, the wasm neutralised, the
    gzips but index.html's) completed here: index.html rewritten (a few KB) and gzipped, the
    folder marked ready and renamed to `cache`, so a half-prepared viewer is never served."""
    import gzip
    import shutil

    index = folder / "index.html"
    data = neutralise_index(index.read_text()).encode()
    index.write_bytes(data)
    (folder / "index.html.gz").write_bytes(gzip.compress(data, compresslevel=6, mtime=0))
    (folder / "ready").write_text("")
    shutil.rmtree(cache, ignore_errors=True)
    os.replace(folder, cache)


PREPARE_TIMEOUT_S = 300  # a Pi 4 gzips the 43 MB wasm in well under a minute


async def _viewer_cache(request: Request) -> Path:
    return await viewer_cache(request.app.state.settings)


async def viewer_cache(settings: Any) -> Path:
    """The prepared viewer's folder, prepared now if it is not (once per rerun version; also at
    the appliance's start, ``prepare_viewer_at_start``). Unavailable when it cannot be."""
    import importlib.metadata

    # The version from the package's metadata: importing rerun only for it costs the appliance
    # tens of MB when no run has imported it yet.
    version = importlib.metadata.version("rerun-sdk")
    cache = Path(settings.data_dir) / "rerun-viewer" / f"{version}-{PREPARED_AS}"
    if (cache / "ready").is_file():
        return cache
    async with _prepare_lock:
        if (cache / "ready").is_file():
            return cache
        # In a child (logs/rerun_files.py), never in the appliance: the 43 MB wasm read, rewritten and
        # gzipped left the appliance ~90 MB larger for good (the allocator keeps what a worker
        # thread touched), and the ``rerun --serve-web`` it copies from (78 MB) is needed only
        # for the copy (issue 30 item 4).
        tmp = cache.with_name(f".{cache.name}.{os.getpid()}.part")
        await asyncio.to_thread(shutil.rmtree, tmp, True)
        async with heavy_turn():  # not while a download's conversion child runs (logs/convert_child.py)
            await _prepare_in_child(tmp, cache)
    return cache


async def prepare_viewer_at_start(settings: Any) -> None:
    """The appliance's start (server/app.py, ``Settings.prepare_viewer_at_start``): the viewer
    prepared while the appliance is at its smallest, not at a class's first live viewer, when
    the appliance, its run and the preparing child (``rerun --serve-web``, ~100 MB) were all
    there at once: the round-1 peak of bench/appliance/practical.py (issue 30 item 4). Once per
    rerun version: afterwards the folder is there and this returns at once. A failure is said in
    the log; the first viewer tries again (and says why to its user)."""
    try:
        await viewer_cache(settings)
    except Unavailable as exc:
        logging.getLogger("xrflab.rerun").warning("rerun viewer not prepared at start: %s", exc)


async def _prepare_in_child(tmp: Path, cache: Path) -> None:
    import sys

    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "xrflab.logs.rerun_files",
        str(tmp),
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        _, err = await asyncio.wait_for(proc.communicate(), PREPARE_TIMEOUT_S)
    except (TimeoutError, asyncio.CancelledError) as exc:
        proc.kill()  # its rerun child gets SIGTERM with it (tied.popen_tied)
        await proc.wait()
        await asyncio.to_thread(shutil.rmtree, tmp, True)
        if isinstance(exc, TimeoutError):
            raise Unavailable(f"the rerun viewer was not prepared within {PREPARE_TIMEOUT_S} s") from None
        raise
    lines = (err or b"").decode(errors="replace").strip().splitlines()
    if proc.returncode != 0:
        await asyncio.to_thread(shutil.rmtree, tmp, True)
        raise Unavailable(f"the rerun viewer could not be prepared: {(lines or [f'exit {proc.returncode}'])[-1]}")
    if lines and lines[-1].startswith("URLs not found"):  # a newer rerun (the CSP still stops them in the browser)
        logging.getLogger("xrflab.rerun").warning("rerun viewer: %s", lines[-1])
    await asyncio.to_thread(finish_viewer, tmp, cache)


@router.get("/rerun/{asset:path}", dependencies=[requires(Perm.WATCH)], include_in_schema=False)
async def rerun_viewer(asset: str, request: Request) -> Response:
    """The rerun web viewer's files, prepared once from rerun's internal server and kept on disk
    (keyed by the rerun version): neutralised (nothing fetched from the internet), gzipped, served
    by us with our caching, auth and Content-Security-Policy. Anything else under /rerun/ (the
    neutralised URLs under /rerun/offline/ among them) is a 404, at once."""
    asset = asset or "index.html"
    if asset not in VIEWER_FILES:
        raise NotFound("no such viewer file", headers={"Content-Security-Policy": VIEWER_CSP})
    cache = await _viewer_cache(request)
    path = cache / asset
    if asset == "index.html" and request.query_params.get("url", "").endswith("/proxy"):
        # A live viewer is loading: its run's recording starts streaming now, not when the viewer's
        # app has started and connected seconds later (LiveProxy.expect_viewer, issue 31 bug 6).
        # Only for a run this user may watch (as the stream itself).
        from ...logs.rerun_servers import LiveProxy

        proxy = LiveProxy.current()
        if proxy is not None and ownership.may_see(ownership.user_of(request), proxy.owner):
            # The proxy's process may have to start (the run's first viewer): on a thread of its
            # own, and the page served meanwhile. Awaited, the page waited for rerun's process to
            # listen (0.2-0.5 s at load 8 on a 2-core machine), and the viewer's whole start (its
            # wasm, its app, its request for the stream) with it; the stream's request comes
            # seconds later, and the read route waits for a start under way (ensure_running).
            threading.Thread(target=proxy.expect_viewer, name="xrf-rerun-expect", daemon=True).start()
    headers = {
        "Cache-Control": "no-cache" if asset == "index.html" else "public, max-age=86400",
        "Content-Security-Policy": VIEWER_CSP,
        "Vary": "Accept-Encoding",
        "X-Content-Type-Options": "nosniff",
        # the uncompressed size: rerun's loader shows its progress from it
        "rerun-final-length": str(path.stat().st_size),
    }
    gz = path.with_name(path.name + ".gz")
    if "gzip" in request.headers.get("accept-encoding", "").lower() and gz.is_file():
        headers["Content-Encoding"] = "gzip"
        return FileResponse(gz, media_type=_MEDIA.get(path.suffix), headers=headers)
    return FileResponse(path, media_type=_MEDIA.get(path.suffix), headers=headers)


# ---- the live stream ------------------------------------------------------------------------


def grpc_error(http_status: int, code: int, message: str) -> Response:
    """A trailers-only gRPC-web answer (status in the headers) that also reads as plain HTTP."""
    return Response(
        status_code=http_status,
        media_type="application/grpc-web+proto",
        headers={"grpc-status": str(code), "grpc-message": urllib.parse.quote(message, safe=" ,.:'()-")},
    )


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


# A viewer connecting while the run's recording does not send (nobody watched: it sends only while
# watched) would be handed, newest first, the proxy's window from before the pause, seconds or
# minutes old, and draw that first (issue 31 bug 6: at the live edge from the first sample). The
# read is counted in first (the recording resumes), and connected to the proxy once the recording
# has sent again (LiveProxy.fresh): its newest samples are then replayed first. At most this long
# (rerun's import at the first viewer, ~1 s; seconds on a loaded machine); not for a run that
# has ended (its window is its end) nor for a viewer that went away.
LIVE_EDGE_WAIT_S = 10.0
LIVE_EDGE_POLL_S = 0.05


async def _live_edge(request: Request, proxy: Any) -> None:
    sup = request.app.state.supervisor
    deadline = asyncio.get_running_loop().time() + LIVE_EDGE_WAIT_S
    while not proxy.fresh() and asyncio.get_running_loop().time() < deadline:
        run = sup.current
        if run is None or run.row.id != proxy.run_id or not run.alive or run.ended.is_set():
            return
        if await request.is_disconnected():
            return
        await asyncio.sleep(LIVE_EDGE_POLL_S)  # polling the recording's thread's stamp (LiveProxy.sent)


@router.post(f"/{SERVICE}/{{method}}", dependencies=[requires_grpc_web(Perm.WATCH)], include_in_schema=False)
async def live_stream(method: str, request: Request) -> Response:
    global _open_streams
    import httpx

    from ...logs.rerun_servers import LiveProxy

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

    # The proxy's process runs only while watched (LiveProxy.ensure_running): started here if not.
    if not proxy.running() and not await asyncio.to_thread(proxy.ensure_running):
        return grpc_error(404, NOT_FOUND, NO_LIVE_STREAM)
    headers = {"content-type": request.headers.get("content-type", "application/grpc-web+proto"), "x-grpc-web": "1"}
    if "grpc-timeout" in request.headers:
        headers["grpc-timeout"] = request.headers["grpc-timeout"]
    watched = proxy  # (narrowed: not None) the run's recording sends while it has readers (logs/rerun_live.py)
    # From here the wait below needs the recording to send: the first reader wakes it at once
    # (LiveProxy.reader_joined: on_viewer), not at its next round.
    watched.reader_joined()
    if method == "ReadMessages" and not watched.fresh():
        try:
            await _live_edge(request, watched)
        except BaseException:  # cancelled (the appliance stops): no reader any more
            watched.reader_left()
            raise
    # No read timeout: a live stream is quiet between runs and that is not an error. The run's
    # proxy is plain HTTP on 127.0.0.1: no TLS and no proxy from the environment. With httpx's
    # defaults, HTTP_PROXY or ALL_PROXY in the appliance's environment (a lab behind a web proxy)
    # sent this loopback request to that proxy (no live stream at all), and each viewer's request
    # made a client that loaded the CA bundle on the event loop: 25-110 ms on a 2-core machine,
    # most of the route's own time before the run's proxy answered (issue 31 bug 6, session 12).
    client = loopback.async_client(timeout=httpx.Timeout(10.0, read=None))
    for attempt in (1, 2):
        try:
            upstream = await client.send(
                client.build_request("POST", f"{proxy.read_url}/{SERVICE}/{method}", content=body, headers=headers),
                stream=True,
            )
            break
        except httpx.TransportError as exc:
            # The process went between its start and this request (an ended run's proxy, which
            # runs only while watched: CI saw "All connection attempts failed" under load, and once
            # a connection closed under the request, an httpx error without a message): started
            # again if it has to be and asked once more (ReadMessages only reads), then the viewer
            # is told.
            logging.getLogger("xrflab.rerun").info(
                "live stream of run %s, attempt %d: %s", proxy.run_id, attempt, loopback.why_failed(exc)
            )
            error: Exception = exc
            if attempt == 1 and await asyncio.to_thread(proxy.ensure_running):
                continue
        except httpx.HTTPError as exc:
            error = exc
        watched.reader_left()
        await client.aclose()
        why = loopback.why_failed(error)
        return grpc_error(502, UNAVAILABLE, f"the live stream of run {proxy.run_id} does not answer: {why}")
    _open_streams += 1
    closed = False

    async def close() -> None:
        nonlocal closed
        global _open_streams
        if not closed:
            closed = True
            _open_streams -= 1
            watched.reader_left()  # the last reader of an ended run: its proxy process stops
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
