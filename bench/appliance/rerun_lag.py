#!/usr/bin/env python3
"""Live rerun lag: how far behind the loop a viewer of the live rerun stream is.

A real appliance on the simulated bench runs a loop at 1 kHz (the RELbot example unless --build).

``browser`` (what a person sees, issue 31 bug 6): Debian's chromium (Playwright, the system
browser) opens the live viewer tab --late s into a run, as the Runs page's "Live plots" does, and
samples the viewer's own state every 250 ms (``window._handle.viewer_state()``: the newest sample of
the run it holds, where its following plots end; tests/xrf_testing/rerun_stream.py
``viewer_newest_ns``). Reported: the app's start, when it first held a sample of the run and how
old that sample was at the opening, how far behind live it was 5/10/20/30 s after it started, and
when it was first within --edge s of live; the viewer thread's longest stalls and its frame rate,
and the console.debug lines that reached the console. Before the run, the same for an empty viewer
(no stream): its own start-up. (The viewer files are prepared and cached before.) To vary one
thing at a time: XRF_RERUN_MEMORY (the live proxy's window, in the appliance's environment),
--viewport (pixels: chromium without a GPU rasterises them on the CPU), --full-size (the live
view's canvas as large as the tab, not the tab script's smaller default), --late. Also when the
page asked for the stream and when its first bytes came (DevTools network events), the time from
the opening to the first sample within --edge s of live, and the tab script's frame gate (frames
drawn / asked for, frontend/rerun-tab.js). The load average
is printed before and after (the machine may be shared: compare runs made back to back).
Where the time before the first drawn sample goes (issue 31 bug 6, ``PHASES``, s after the
opening): the wasm's fetch (resource timing), its compile and instantiation (WebAssembly's entry
points), the app's start, the live stream asked for (by the tab script at the page's load, or by
the viewer) and its first data, and the first of the viewer's frames that holds a sample of the
run (its state at the end of each frame callback) with how far behind live that sample was then,
and when the next frame ended (its pixels are on screen by then). "Behind at the first sample
drawn" = the end of that frame's callback (the viewer ingests and draws in it; its pixels are
rasterised right after) minus the newest sample its state holds then, in two parts (session 13):
the frame's own time (its callback's start to its end: the viewer's code and software WebGL,
which no page script shortens) and how old that sample already was at the frame's start (the
stream's batching and what the tab handed over first); ``SUMMARY``, one line a run, and
``TIMELINE``, the frames around it and the reads of a stream on the page's thread (s after the
opening, KB). The browser has a profile on
disk, as a person's has (its HTTP cache keeps the wasm, its code cache the compiled module):
``--fresh-profile`` for Playwright's off-the-record context instead; ``--cold``: a profile on disk
that has never loaded the viewer (its files prepared by the appliance over HTTP, no warm-up page
and no empty viewer in the browser), a person's very first opening. ``--reopen S``: the opening
measured is a second one (the live viewer opened before until it drew data, closed, S s without
a viewer).

``wire`` (issue 31 bug 6, session 12): the viewer's stream request at the wire, as its tab makes it:
the viewer's page (which starts the run's recording), --ask-after s later the stream's request
(the tab asks once the wasm is compiled), read --read s; in each of --runs runs the run's first
viewer (the Runs page's ``soon`` before it) and --reopens more, --gap s after the last one left.
Per opening: the answer's headers, its first bytes and the first data frame with a sample of the
run (s after the request) and how old that sample was then; p50/max per kind.

Headless cases (at the wire, not what a person sees): headless viewers read the run's live stream
as the web viewer does, by gRPC-web through the appliance's route (login cookie, same Origin), each
in a process of its own. Each data frame is decoded as far as its chunk's ``time`` index
(tests/xrf_testing/rerun_stream.py: protobuf by hand, LZ4 block, Arrow IPC): the newest sample it
carries, in wall-clock ns (the loop's sample time + the run's wall offset, logs/rerun_live.py). lag =
the frame's arrival wall time - that sample's wall time, over every frame that carries one.
Cases (each a fresh run): 1 viewer, N viewers (--viewers, default 5), 1 viewer with the other core
loaded (``stress-ng --cpu 1`` pinned to the CPU the loop is not on). In each, after the live
window a late viewer connects: its catch-up time is from connecting until the first frame within
--edge s of the loop. Not a timed test; prints figures.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

from _common import REPO_ROOT, appliance, pct

sys.path.insert(0, str(REPO_ROOT / "tests"))


# ---- a viewer (own process) ---------------------------------------------------------------------


def viewer(url: str, seconds: float, edge_s: float) -> None:
    """Read the live stream for `seconds` (or until caught up when seconds < 0: a late viewer);
    print one JSON line: [arrival_ns, newest_ns] per frame with a time, the connect time, counts."""
    import httpx

    from xrf_testing.grpcweb import EMPTY_REQUEST, GRPC_WEB, READ_MESSAGES, split_frames
    from xrf_testing.harness import ADMIN_PASSWORD, ADMIN_USER, login_client
    from xrf_testing.rerun_stream import STORE_RECORDING, chunk_of

    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    samples: list[tuple[int, int]] = []
    frames = nbytes = 0
    connect_ns = time.time_ns()
    caught_up_ns = None
    end = time.monotonic() + abs(seconds)
    with http.stream(
        "POST", READ_MESSAGES, content=EMPTY_REQUEST, headers=GRPC_WEB, timeout=httpx.Timeout(10.0, read=30.0)
    ) as r:
        if r.status_code != 200:
            raise SystemExit(f"the live stream answered {r.status_code} {r.headers.get('grpc-message', '')}")
        rest = b""
        for raw in r.iter_raw():
            arrival = time.time_ns()
            nbytes += len(raw)
            got, rest = split_frames(rest + raw)
            for flag, payload in got:
                if flag != 0x00:
                    continue
                frames += 1
                chunk = chunk_of(payload)
                if chunk is None or chunk.store_kind != STORE_RECORDING or chunk.newest_time_ns is None:
                    continue
                samples.append((arrival, chunk.newest_time_ns))
                if caught_up_ns is None and arrival - chunk.newest_time_ns <= edge_s * 1e9:
                    caught_up_ns = arrival
            if time.monotonic() > end or (seconds < 0 and caught_up_ns is not None):
                break
    http.close()
    print(
        json.dumps(
            {
                "connect_ns": connect_ns,
                "caught_up_ns": caught_up_ns,
                "frames": frames,
                "bytes": nbytes,
                "samples": samples,
            }
        ),
        flush=True,
    )


def spawn_viewer(url: str, seconds: float, edge_s: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, __file__, "--viewer-worker", url, str(seconds), str(edge_s)], stdout=subprocess.PIPE, text=True
    )


def collect(proc: subprocess.Popen[str], timeout: float) -> dict:
    out, _ = proc.communicate(timeout=timeout)
    if proc.returncode:
        raise SystemExit(f"a viewer failed (exit {proc.returncode})")
    return json.loads(out.strip().splitlines()[-1])


# ---- one case -----------------------------------------------------------------------------------


def start_loop(server, build: str) -> dict:
    run = server.start_run(build)
    with server.ws() as ws:
        ws.command("initialise")
        ws.wait_state("INITIALISED", timeout=10)
        ws.command("start")
        ws.wait_state("RUN", timeout=10)
    deadline = time.monotonic() + 20  # the run's live proxy starts beside the run
    while server.http.get("/api/logs/rerun").json()["live_run"] != run["id"]:
        if time.monotonic() > deadline:
            raise SystemExit("the run's live stream did not start")
        time.sleep(0.1)
    return run


# ---- the footprint case -------------------------------------------------------------------------


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _rerun_children(root: int) -> dict[str, tuple[int, float]]:
    """The appliance's rerun processes below `root` (any depth): {"serve-web"|"serve-grpc": (pid, MB)}."""
    out: dict[str, tuple[int, float]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            argv = open(f"/proc/{entry}/cmdline", "rb").read().split(b"\0")
            ppid, pid = int(open(f"/proc/{entry}/stat").read().rsplit(")", 1)[1].split()[1]), int(entry)
            while ppid not in (0, 1, root):  # a descendant of the appliance?
                ppid = int(open(f"/proc/{ppid}/stat").read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == root and argv and argv[0].endswith(b"rerun"):
            for mode in ("serve-web", "serve-grpc"):
                if f"--{mode}".encode() in argv:
                    out[mode] = (pid, _rss_mb(pid))
    return out


def footprint_case(server, build: str, watch_s: float) -> list[tuple[str, float, dict]]:
    """RSS (MB, /proc/<pid>/status VmRSS) of the appliance and its rerun children: with a run
    streaming; after a browser opened the viewer once and closed it (60 s later); then the live
    proxy every minute of --watch."""
    from playwright.sync_api import sync_playwright

    from xrf_testing.harness import CHROMIUM_ARGS, session_cookies

    rows = []
    app = server.proc.pid

    def row(what: str) -> None:
        rows.append((what, _rss_mb(app), _rerun_children(app)))

    start_loop(server, build)
    time.sleep(30)
    row("run streaming 30 s, no viewer yet")
    chromium = os.environ.get("XRF_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        ctx = browser.new_context()
        ctx.add_cookies(session_cookies(server.http, server.url))
        page = ctx.new_page()
        page.goto(server.url + "/rerun/index.html", timeout=600_000)
        page.wait_for_function("() => window._handle !== undefined", timeout=600_000)
        row("viewer open")
        browser.close()
    time.sleep(60)
    row("viewer closed 60 s ago")
    for minute in range(1, int(watch_s // 60) + 1):
        time.sleep(60)
        row(f"+{minute} min")
    server.stop_run()
    return rows


# ---- the browser case ---------------------------------------------------------------------------

SAMPLE = """window._xrfSamples = []; setInterval(() => {
  try { window._xrfSamples.push([Date.now(), Array.from(window._handle.viewer_state())]); } catch (e) {}
}, 250);"""
# Before the page's own scripts: a 100 ms timer and an animation-frame counter on the viewer's main
# thread, from the opening on. A gap between two timer runs is a stretch the thread was busy (the
# viewer neither ingests nor draws then); frames counted per second are the browser's, which
# while the viewer follows live data are the viewer's own.
TICKS = """window._xrfTicks = []; window._xrfFrames = [];
setInterval(() => window._xrfTicks.push(Date.now()), 100);
(function frame() { window._xrfFrames.push(Date.now()); requestAnimationFrame(frame); })();"""


# Before the page's own scripts too: where the time before the first drawn sample goes, as wall
# times (ms, performance.timeOrigin + now()): the wasm's fetch (resource timing, read at the end),
# its compile and instantiation (WebAssembly's entry points wrapped: index.html's loader calls
# them), the app's start (index.html sets window._handle when WebHandle.start() resolved), and
# each of the viewer's frames until it held a sample of the run: the viewer's state at the end of
# every frame callback (the frame that ingests a sample also draws it; its pixels are rasterised
# by the GPU process right after), kept when it changed, decoded here.
PHASES = """(() => {
  const now = () => performance.timeOrigin + performance.now();
  const m = window._xrfMarks = {}, mark = (k) => { if (!(k in m)) m[k] = now(); };
  for (const name of ["compile", "compileStreaming", "instantiate", "instantiateStreaming"]) {
    const f = WebAssembly[name];
    if (typeof f !== "function") continue;
    WebAssembly[name] = function (...a) {
      mark("wasm_" + name + "_start");
      return f.apply(this, a).then((r) => { mark("wasm_" + name + "_end"); return r; });
    };
  }
  let handle;
  Object.defineProperty(window, "_handle", { configurable: true, get: () => handle,
    set: (v) => { handle = v; mark("app_started"); } });
  // each read of a stream on this thread that brought bytes (the tab script's early reads before
  // session 13, the viewer's): [when, bytes]; the wasm's download is not read this way
  window._xrfReads = [];
  const read = ReadableStreamDefaultReader.prototype.read;
  ReadableStreamDefaultReader.prototype.read = function (...a) {
    return read.apply(this, a).then((r) => {
      if (!r.done && r.value && window._xrfReads.length < 400) window._xrfReads.push([now(), r.value.byteLength]);
      return r;
    });
  };
  // WebGL shader compiles and program links (the viewer makes its render pipelines when it first
  // draws plots: session 14), counted per frame callback below
  const gl = window._xrfGl = { compiles: 0, links: 0 };
  for (const C of [window.WebGL2RenderingContext, window.WebGLRenderingContext]) {
    if (!C) continue;
    const compile = C.prototype.compileShader, link = C.prototype.linkProgram;
    C.prototype.compileShader = function (...a) { gl.compiles += 1; return compile.apply(this, a); };
    C.prototype.linkProgram = function (...a) { gl.links += 1; return link.apply(this, a); };
  }
  window._xrfFrameStates = [];
  window._xrfGlFrames = [];  // [began, ended, compiles, links] of each frame callback that compiled
  let last = "", frames = 0, lastT = null;
  const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => raf((t) => {
    const began = now();  // the viewer ingests what its stream brought at the start of its frame
    const c0 = gl.compiles, l0 = gl.links;
    cb(t);
    const c = gl.compiles - c0, l = gl.links - l0;
    if ((c || l) && window._xrfGlFrames.length < 100) window._xrfGlFrames.push([began, now(), c, l]);
    if (!handle || window._xrfFrameStates.length > 400) return;
    if (t !== lastT) { lastT = t; frames += 1; }  // one frame, however many callbacks it runs
    let st;
    try { st = Array.from(handle.viewer_state()); } catch (e) { return; }
    const key = st.join(",");
    if (key !== last) { last = key; window._xrfFrameStates.push([now(), frames, st, began, c, l]); }
    else if (window._xrfFrameStates.length) window._xrfFrameStates.push([now(), frames, null, began, c, l]);
  });
})();"""
MARKS = """(() => {
  const r = performance.getEntriesByType("resource").find((e) => e.name.endsWith("re_viewer_bg.wasm"));
  const o = performance.timeOrigin, f = window.xrfRerunTab && xrfRerunTab.frames ? xrfRerunTab.frames() : {};
  return { ...window._xrfMarks, nav_start: o,
    wasm_fetch_start: r && o + r.fetchStart, wasm_response_start: r && o + r.responseStart,
    wasm_response_end: r && o + r.responseEnd, wasm_transfer_bytes: r && r.transferSize,
    stream_asked: f.streamAt, viewer_asked: f.viewerAskedAt, stream_answered_js: f.answeredAt,
    stream_first_data: f.firstDataAt, early: f.early, held_groups: f.heldGroups, held_frames: f.heldFrames,
    held_newest_age_ms: f.heldNewestAgeMs,
    worker_started: f.worker && f.worker.started, worker_asked: f.worker && f.worker.asked,
    worker_answered: f.worker && f.worker.answered, worker_first_read: f.worker && f.worker.firstRead,
    warmup_sent: f.warmup && f.warmup.sentAt, warmup_drawn: f.warmup && f.warmup.drawnAt,
    warmup_closed: f.warmup && f.warmup.closedAt, warmup_state: f.warmup ? f.warmup.state : "none",
    gl_frames: window._xrfGlFrames, states: window._xrfFrameStates, reads: window._xrfReads };
})()"""


def phases(page, opened_ns: int, recording: str) -> dict[str, float]:
    """The PHASES marks as s after the opening, and the first frame that held a sample of the run:
    when it ended, how many frames the viewer had drawn by then, and how far behind live it was."""
    from xrf_testing.rerun_stream import viewer_newest_ns

    raw = page.evaluate(MARKS)
    out = {k: v / 1e3 - opened_ns / 1e9 for k, v in raw.items() if isinstance(v, int | float) and v > 1e12}
    out["wasm_transfer_MB"] = (raw.get("wasm_transfer_bytes") or 0) / 1e6
    out["early"] = raw.get("early") or "-"  # the tab script's stream asked for at the page's load
    # what that early stream brought before the viewer asked: bursts and messages (frontend/rerun-tab.js)
    out["held"] = f"{raw.get('held_groups', '-')} bursts, {raw.get('held_frames', '-')} messages"
    if raw.get("held_newest_age_ms") is not None:  # (the worker's: when its newest burst came)
        out["held"] += f", the newest {raw['held_newest_age_ms'] / 1e3:.2f} s old"
    out["warmup"] = raw.get("warmup_state") or "none"  # the tab's warm-up (frontend/rerun-tab.js, session 14)
    # the frame callbacks that compiled shaders: when (s after the opening), how long, how many
    out["gl_frames"] = " ".join(
        f"{b / 1e3 - opened_ns / 1e9:.2f}+{(e - b) / 1e3:.2f}s:{c}/{k}" for b, e, c, k in raw.get("gl_frames") or []
    )
    states = raw.get("states") or []
    for i, (t_ms, n, state, began_ms, compiles, links) in enumerate(states):
        newest = viewer_newest_ns(bytes(state), recording) if state is not None else None
        if newest is not None:
            out["first_drawn"] = t_ms / 1e3 - opened_ns / 1e9
            out["first_drawn_behind"] = t_ms / 1e3 - newest / 1e9
            out["first_drawn_frame"] = n
            # "behind" in two: the frame's own time (its callback, from its start, where the viewer
            # ingests, to its end: the viewer's code, software WebGL), and how old the newest sample
            # it ingested was when the frame began (the stream, and the order it was handed over)
            out["first_drawn_began"] = began_ms / 1e3 - opened_ns / 1e9
            out["first_frame_own_s"] = (t_ms - began_ms) / 1e3
            out["first_drawn_stale"] = began_ms / 1e3 - newest / 1e9
            out["first_frame_gl"] = f"{compiles}/{links}"  # shader compiles / program links in it
            # the app's frames before it (s each: a frame that ingests and draws nothing new is short)
            out["frames_before"] = " ".join(f"{(t - b) / 1e3:.2f}" for t, _, _, b, *_ in states[max(0, i - 4) : i])
            # the frame after it: what the first frame drew is on screen when this one ended at the
            # latest (the first plots' shaders may be compiled in either)
            # the frames up to it (s after the opening: began-ended, how old its newest sample was at
            # its end) and the reads with bytes on the page's thread meanwhile (s, KB)
            reads = raw.get("reads") or []
            lines = []
            for t, _, st, b, *_ in states[max(0, i - 4) : i + 3]:
                nw = viewer_newest_ns(bytes(st), recording) if st is not None else None
                age = f" newest {t / 1e3 - nw / 1e9:.2f} s old" if nw is not None else ""
                lines.append(f"frame {b / 1e3 - opened_ns / 1e9:.2f}-{t / 1e3 - opened_ns / 1e9:.2f}{age}")
            first_ms = states[max(0, i - 4)][3]
            got = [
                f"{r / 1e3 - opened_ns / 1e9:.2f}:{kb / 1e3:.0f}"
                for r, kb in reads
                if first_ms - 3000 <= r <= t_ms + 1500
            ]
            out["timeline"] = "; ".join(lines) + " | reads (s:KB) " + " ".join(got)
            # Its plots: the viewer builds its render pipelines (shader compiles) when it first draws
            # plots, and that can be a frame or two after the first that holds a sample (session 14:
            # seen at 0.1-0.6 s after it without the warm-up). No plot with data is on screen before
            # the last frame that compiled has ended: "plots drawn" is the end of the first frame
            # holding a sample, or of the last compiling frame that began at or after it (within 5 s),
            # whichever is later, and "behind" then is against the newest sample the viewer held at
            # that moment. (With the tab's warm-up every compile is before the run's data.)
            compiling = [e for b, e, *_ in raw.get("gl_frames") or [] if began_ms <= b <= began_ms + 5000]
            plots_ms = max([t_ms, *compiling])
            held_then = [st for t, _, st, *_ in states if st is not None and t <= plots_ms]
            newest_then = viewer_newest_ns(bytes(held_then[-1]), recording) if held_then else newest
            out["plots_drawn"] = plots_ms / 1e3 - opened_ns / 1e9
            out["plots_drawn_behind"] = plots_ms / 1e3 - (newest_then or newest) / 1e9
            later = next((t for t, m, *_ in states[i + 1 :] if m > n), None)
            if later is not None:
                out["next_frame_end"] = later / 1e3 - opened_ns / 1e9
                out["next_frame_end_behind"] = later / 1e3 - newest / 1e9
            break
    return out


def _thread(page, opened_ns: int, app_ns: int) -> dict:
    """The viewer thread's longest stalls after its app started (s, and when: s after the opening)
    and its median frame rate over the sampled seconds."""
    ticks, frames = page.evaluate("[window._xrfTicks, window._xrfFrames]")
    app = (app_ns - opened_ns) / 1e9
    ticks = [t / 1e3 - opened_ns / 1e9 for t in ticks]
    gaps = sorted(((b - a, a) for a, b in zip(ticks, ticks[1:]) if b > app), reverse=True)
    frames = [t / 1e3 - opened_ns / 1e9 for t in frames]
    per_s = sorted(
        sum(1 for f in frames if s <= f < s + 1) for s in range(int(app) + 1, int(ticks[-1]) if ticks else 0)
    )
    return {"stalls": gaps[:3], "fps_median": per_s[len(per_s) // 2] if per_s else float("nan")}


def chromium_cpu_s() -> dict[str, float]:
    """CPU seconds (user + system) of this script's chromium (its descendants: the machine may run
    other browsers), by process type (--type=renderer, gpu-process, ...; the browser process has
    none). The GPU process is where software WebGL (SwiftShader) rasterises the viewer's frames."""
    import re

    out: dict[str, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            raw = open(f"/proc/{entry}/cmdline", "rb").read().replace(b"\0", b" ")
            if b"chromium" not in raw.split(b" ", 1)[0]:
                continue
            stat = open(f"/proc/{entry}/stat").read().rsplit(")", 1)[1].split()
            ppid = int(stat[1])
            while ppid not in (0, 1, os.getpid()):
                ppid = int(open(f"/proc/{ppid}/stat").read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError):
            continue
        if ppid != os.getpid():
            continue
        m = re.search(rb"--type=([a-z-]+)", raw)
        kind = m.group(1).decode() if m else "browser"
        out[kind] = out.get(kind, 0.0) + (int(stat[11]) + int(stat[12])) / tick
    return out


def empty_viewer(ctx, url: str, watch_s: float) -> dict:
    """The viewer's own start-up, no stream: app start and its thread after it (no data to draw)."""
    page = ctx.new_page()
    page.add_init_script(TICKS)
    opened_ns = time.time_ns()
    page.goto(url + "/rerun/index.html", timeout=120_000)
    page.wait_for_function("() => window._handle !== undefined", timeout=600_000)
    app_ns = time.time_ns()
    end = time.monotonic() + watch_s
    while time.monotonic() < end:
        time.sleep(0.5)  # time passing: the viewer idles
    thread = _thread(page, opened_ns, app_ns)
    page.close()
    return {"app_start_s": (app_ns - opened_ns) / 1e9, **thread}


def _stream_timing(ctx, page) -> tuple[dict[str, int], list[int]]:
    """When the page asked for the live stream and when its first bytes came (wall ns), from the
    DevTools protocol's network events (their own timestamps: Playwright's sync API dispatches
    events late, while the script sleeps); and when each of its bytes reached the browser's network
    layer (wall ns: not delayed by the page's busy main thread)."""
    cdp = ctx.new_cdp_session(page)
    cdp.send("Network.enable")
    out: dict[str, int] = {}
    arrivals: list[int] = []
    req: dict[str, tuple[float, float]] = {}  # requestId -> (monotonic s, wall s)

    def sent(e: dict) -> None:
        if e["request"]["url"].endswith("/ReadMessages") and not req:
            req[e["requestId"]] = (e["timestamp"], e["wallTime"])
            out["stream_requested"] = int(e["wallTime"] * 1e9)

    def wall(e: dict) -> int | None:
        t0 = req.get(e["requestId"])
        return None if t0 is None else int((t0[1] + e["timestamp"] - t0[0]) * 1e9)

    def answered(e: dict) -> None:
        if (t := wall(e)) is not None:
            out.setdefault("stream_answered", t)

    def data(e: dict) -> None:
        if (t := wall(e)) is not None and e.get("dataLength", 0) > 0:
            out.setdefault("stream_first_bytes", t)
            arrivals.append(t)

    cdp.on("Network.requestWillBeSent", sent)
    cdp.on("Network.responseReceived", answered)
    cdp.on("Network.dataReceived", data)
    return out, arrivals


# The tab script's "Full-size view" choice (frontend/rerun-tab.js FULL_KEY), set before the page loads.
FULL_SIZE = "try { localStorage.setItem('xrf-rerun-live-full', '1'); } catch (e) {}"
# ...and its "every frame the viewer asks for" switch (frontend/rerun-tab.js: frames on demand otherwise).
ALL_FRAMES = "try { localStorage.setItem('xrf-rerun-live-frames', 'all'); } catch (e) {}"


_NOT_TIMES = (
    "first_drawn_behind",
    "first_frame_own_s",
    "first_drawn_stale",
    "next_frame_end_behind",
    "first_drawn_frame",
    "wasm_transfer_MB",
    "early",
    "held",
    "net_gap_s",
    "frames_before",
    "timeline",
    "warmup",
    "gl_frames",
    "first_frame_gl",
    "plots_drawn_behind",
)


def browser_case(
    server,
    build: str,
    late_s: float,
    watch_s: float,
    edge_s: float,
    viewport: dict,
    full_size: bool = False,
    all_frames: bool = False,
    fresh_profile: bool = False,
    cold: bool = False,
    reopen_s: float = 0.0,
    via_runs_s: float | None = None,
    stress_workers: int = 0,
) -> dict:
    import tempfile
    import urllib.parse

    from playwright.sync_api import sync_playwright

    from xrf_testing.harness import CHROMIUM_ARGS, session_cookies
    from xrf_testing.rerun_stream import viewer_newest_ns

    chromium = os.environ.get("XRF_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        raise SystemExit("the browser case needs Debian's chromium (or XRF_CHROMIUM)")
    stress = None  # --browser-stress: CPU load from the run's start on
    with sync_playwright() as p:
        # A browser profile on disk, as a person's chromium has (a temporary one, removed after):
        # Playwright's default context is off the record, whose in-memory HTTP cache does not keep
        # the viewer's 14 MB wasm (it was fetched again at every opening) and which keeps no
        # compiled wasm code. --fresh-profile: that default context, to compare.
        profile = None if fresh_profile else tempfile.mkdtemp(prefix="xrf-rerun-lag-profile-")
        if profile is None:
            browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            ctx = browser.new_context(viewport=viewport)
        else:
            browser = ctx = p.chromium.launch_persistent_context(
                profile, executable_path=chromium, args=CHROMIUM_ARGS, viewport=viewport
            )
        try:
            ctx.add_cookies(session_cookies(server.http, server.url))
            if cold:  # the files prepared by the appliance, none of them in this browser's caches
                assert server.http.get("/rerun/index.html", timeout=600).status_code == 200
                empty = {"app_start_s": float("nan"), "stalls": [], "fps_median": float("nan")}
            else:
                warm = ctx.new_page()  # the viewer's files prepared and in the cache: not measured
                warm.goto(server.url + "/rerun/index.html", timeout=600_000)
                warm.wait_for_function("() => window._handle !== undefined", timeout=600_000)
                warm.close()
                empty = empty_viewer(ctx, server.url, min(watch_s, 15.0))
            if stress_workers:
                stress = subprocess.Popen(
                    [
                        "stress-ng",
                        "--cpu",
                        str(stress_workers),
                        "--timeout",
                        f"{int(late_s + watch_s + 600)}s",
                        "--quiet",
                    ],
                    stdout=subprocess.DEVNULL,
                )
            run = start_loop(server, build)
            started = time.monotonic()
            while time.monotonic() - started < late_s:
                time.sleep(0.2)
            info = server.http.get("/api/logs/rerun").json()
            live = server.url + "/rerun/?url=" + urllib.parse.quote(info["live_url"], safe="")
            if reopen_s:
                # A person's second opening: the same viewer opened on the run before, until it drew
                # data and a few seconds more, then closed; nobody watches for --reopen s.
                first = ctx.new_page()
                first.goto(live, timeout=120_000)
                first.wait_for_function("() => window._handle !== undefined", timeout=600_000)
                end = time.monotonic() + 60
                while not first.evaluate("xrfRerunTab.frames().firstDataAt !== null") and time.monotonic() < end:
                    time.sleep(0.5)  # polling: the first opening's data
                time.sleep(5)  # time passing: it draws its first plots (shaders compiled, cached)
                first.close()
                time.sleep(reopen_s)  # time passing: nobody watches
            scripts = [TICKS, PHASES] + [FULL_SIZE] * full_size + [ALL_FRAMES] * all_frames
            debug_lines = [0]
            if via_runs_s is None:
                page = ctx.new_page()
                for script in scripts:
                    page.add_init_script(script)
                wire, arrivals = _stream_timing(ctx, page)
                page.on("console", lambda m: m.type == "debug" and debug_lines.__setitem__(0, debug_lines[0] + 1))
                opened_ns = time.time_ns()
                page.goto(live, timeout=120_000)
            else:
                # As a person opens it: the dashboard's Runs page, --via-runs-page s of looking at
                # it, then its "Live plots" button, which opens the viewer in a tab of its own
                # (frontend/pages/runs.js). Measured from the click. The samplers go into every page
                # of the context (only the viewer's tab runs them). The stream's network events:
                # from a DevTools session on the new tab, opened as soon as the tab exists (its
                # stream is asked for ~0.6 s or more later); their times are the network layer's,
                # not the page's main thread, which the viewer's start keeps busy (session 12: the
                # tab script's own marks of the answer came 0.5-0.8 s after the network's).
                for script in scripts:
                    ctx.add_init_script("if (location.pathname.startsWith('/rerun/')) {\n" + script + "\n}")
                dash = ctx.new_page()
                dash.goto(server.url + "/#runs", timeout=120_000)
                dash.wait_for_selector("#rr-live", state="visible", timeout=60_000)
                time.sleep(via_runs_s)  # time passing: a person reads the page, then clicks
                with ctx.expect_page(timeout=120_000) as popup:
                    opened_ns = time.time_ns()
                    dash.click("#rr-live")
                page = popup.value
                wire, arrivals = _stream_timing(ctx, page)
                page.on("console", lambda m: m.type == "debug" and debug_lines.__setitem__(0, debug_lines[0] + 1))
            page.wait_for_function("() => window._handle !== undefined", timeout=600_000)
            app_ns = time.time_ns()
            print(f"browser: opened at {opened_ns / 1e9:.4f} (wall s)", file=sys.stderr, flush=True)
            load_at_open = os.getloadavg()[0]
            page.evaluate(SAMPLE)
            cpu0, frames0, t0 = chromium_cpu_s(), page.evaluate("window._xrfFrames.length"), time.monotonic()
            end = time.monotonic() + watch_s
            while time.monotonic() < end:
                time.sleep(0.5)  # time passing: the viewer follows the run
            cpu1, frames1, t1 = chromium_cpu_s(), page.evaluate("window._xrfFrames.length"), time.monotonic()
            raw = page.evaluate("window._xrfSamples")
            marks = phases(page, opened_ns, f"run-{run['id']}")
            if "first_drawn_began" in marks:  # the stream's newest bytes at the network by then
                began_ns = opened_ns + marks["first_drawn_began"] * 1e9
                got = [a for a in arrivals if a <= began_ns]
                if got:
                    marks["net_gap_s"] = (began_ns - max(got)) / 1e9
            thread = _thread(page, opened_ns, app_ns)
            gate = page.evaluate("window.xrfRerunTab && xrfRerunTab.frames ? xrfRerunTab.frames() : null")
            canvas = page.evaluate(
                "(() => { const c = document.getElementById('the_canvas_id'); return [c.width, c.height]; })()"
            )
        finally:
            if stress is not None:
                stress.terminate()
                stress.wait()
            browser.close()
            if profile is not None:
                shutil.rmtree(profile, ignore_errors=True)
            server.stop_run()
    samples = []  # (s since the app started, s behind live, newest sample's age at the opening)
    for t_ms, state in raw:
        newest = viewer_newest_ns(bytes(state), f"run-{run['id']}")
        if newest is not None:
            samples.append((t_ms / 1e3 - app_ns / 1e9, t_ms / 1e3 - newest / 1e9, (opened_ns - newest) / 1e9))

    def behind_at(t: float) -> float:
        after = [b for s, b, _ in samples if s >= t]
        return after[0] if after else float("nan")

    edge = next((s for s, b, _ in samples if b <= edge_s), float("nan"))
    app_s = (app_ns - opened_ns) / 1e9
    return {
        "run": run["id"],
        "run_age_s": late_s,
        "load_at_open": load_at_open,
        "app_start_s": (app_ns - opened_ns) / 1e9,
        "first_s": samples[0][0] if samples else float("nan"),
        "first_age_s": samples[0][2] if samples else float("nan"),
        "behind": {t: behind_at(t) for t in (0, 5, 10, 20, 30)},
        "edge_s": edge,
        "edge_from_open_s": edge + app_s,
        # stayed within edge_s of live from then on (every later sample of its state)
        "kept_s": next(
            (s for i, (s, _, _) in enumerate(samples) if all(b <= edge_s for _, b, _ in samples[i:])), float("nan")
        ),
        "worst_after": {t: max((b for s, b, _ in samples if s >= t), default=float("nan")) for t in (1, 5)},
        "wire": {k: (v - opened_ns) / 1e9 for k, v in wire.items()},
        "samples": len(raw),
        "thread": thread,
        "debug_lines": debug_lines[0],
        "empty": empty,
        "canvas": canvas,
        "gate": gate,
        "phases": marks,
        "frames_per_s": (frames1 - frames0) / (t1 - t0),
        "cpu_per_s": {k: (cpu1[k] - cpu0.get(k, 0.0)) / (t1 - t0) for k in cpu1},
    }


# ---- the wire case: the viewer's stream request, as the tab makes it -----------------------------


def opening(server, live_url: str, ask_after_s: float, read_s: float, soon: bool) -> dict:
    """One opening of the live viewer as its tab does it, at the wire: the Runs page's `soon`
    (when `soon`), the viewer's page (which starts the run's recording, LiveProxy.expect_viewer),
    `ask_after_s` later the stream's request (the tab script asks once the viewer's wasm is
    compiled), read for `read_s`. Wall times (s) after the request: the answer's headers, its
    first bytes, the first data frame with a sample of the run and how old that sample was when it
    came, and the newest sample of the first burst (its frames within 0.1 s of the first)."""
    import urllib.parse

    import httpx

    from xrf_testing.grpcweb import EMPTY_REQUEST, GRPC_WEB, READ_MESSAGES, split_frames
    from xrf_testing.rerun_stream import STORE_RECORDING, chunk_of

    if soon:
        server.http.get("/api/logs/rerun", params={"soon": "true"})
    page_ns = time.time_ns()
    r = server.http.get("/rerun/index.html?url=" + urllib.parse.quote(live_url, safe=""))
    assert r.status_code == 200, r.status_code
    served_ns = time.time_ns()
    time.sleep(max(0.0, ask_after_s - (served_ns - page_ns) / 1e9))  # time passing: the viewer's wasm compiles
    out: dict = {"page_s": (served_ns - page_ns) / 1e9}
    asked_ns = time.time_ns()
    end = time.monotonic() + read_s
    first_data = None
    with server.http.stream(
        "POST", READ_MESSAGES, content=EMPTY_REQUEST, headers=GRPC_WEB, timeout=httpx.Timeout(10.0, read=30.0)
    ) as res:
        out["headers_s"] = (time.time_ns() - asked_ns) / 1e9
        rest = b""
        for raw in res.iter_raw():
            arrival = time.time_ns()
            out.setdefault("first_bytes_s", (arrival - asked_ns) / 1e9)
            got, rest = split_frames(rest + raw)
            for flag, payload in got:
                chunk = chunk_of(payload) if flag == 0 else None
                if chunk is None or chunk.store_kind != STORE_RECORDING or chunk.newest_time_ns is None:
                    continue
                if first_data is None:
                    first_data = arrival
                    out["first_data_s"] = (arrival - asked_ns) / 1e9
                    out["first_data_age_s"] = (arrival - chunk.newest_time_ns) / 1e9
                    out["burst_newest_age_s"] = out["first_data_age_s"]
                elif arrival - first_data <= 100_000_000:
                    out["burst_newest_age_s"] = min(out["burst_newest_age_s"], (arrival - chunk.newest_time_ns) / 1e9)
            if time.monotonic() > end:
                break
    out["asked_wall"] = asked_ns / 1e9
    return out


def wire_case(
    server,
    build: str,
    runs: int,
    reopens: int,
    late_s: float,
    gap_s: float,
    ask_after_s: float,
    read_s: float,
    stress_workers: int = 0,
) -> list[tuple[str, float, dict]]:
    """`runs` runs; in each, --late s in, its first viewer (the Runs page's `soon` 2 s before, as
    a person looks at the page), then `reopens` more openings, each `gap_s` after the previous
    one closed: (which, load average, opening())."""
    import pyarrow  # noqa: F401  (the frames' decoder's: imported before, not inside a measurement)

    server.http.get("/rerun/index.html", timeout=600)  # the viewer's files prepared: not measured
    rows = []
    for _ in range(runs):
        run = start_loop(server, build)
        stress = None
        if stress_workers:  # from the run's start, like the browser case's --browser-stress
            stress = subprocess.Popen(
                ["stress-ng", "--cpu", str(stress_workers), "--timeout", "600s", "--quiet"], stdout=subprocess.DEVNULL
            )
        try:
            started = time.monotonic()
            while time.monotonic() - started < late_s - 2:
                time.sleep(0.2)
            server.http.get("/api/logs/rerun", params={"soon": "true"})
            time.sleep(2)  # time passing: a person looks at the Runs page
            live_url = server.http.get("/api/logs/rerun").json()["live_url"]
            for i in range(reopens + 1):
                if i:
                    time.sleep(gap_s)  # time passing: nobody watches
                load = os.getloadavg()[0]
                res = opening(server, live_url, ask_after_s, read_s, soon=False)
                res["run"] = run["id"]
                rows.append(("first" if i == 0 else "reopen", load, res))
                print(f"wire {rows[-1]}", file=sys.stderr, flush=True)
        finally:
            if stress is not None:
                stress.terminate()
                stress.wait()
            server.stop_run()
    return rows


def run_case(server, build: str, viewers: int, seconds: float, edge_s: float, stress_cpu: int | None) -> dict:
    stress = None
    if stress_cpu is not None:
        stress = subprocess.Popen(
            ["stress-ng", "--cpu", "1", "--taskset", str(stress_cpu), "--timeout", f"{int(seconds + 120)}s", "--quiet"],
            stdout=subprocess.DEVNULL,
        )
    try:
        run = start_loop(server, build)
        started = time.monotonic()
        procs = [spawn_viewer(server.url, seconds, edge_s) for _ in range(viewers)]
        live = [collect(p, seconds + 120) for p in procs]
        age = time.monotonic() - started
        late = collect(spawn_viewer(server.url, -600.0, edge_s), 660)
    finally:
        if stress is not None:
            stress.terminate()
            stress.wait()
        server.stop_run()
    lags: list[float] = []
    for v in live:
        caught = v["caught_up_ns"] or 0
        lags += [(a - t) / 1e6 for a, t in v["samples"] if a >= caught]  # the replay on connect is not lag
    catch_up = (late["caught_up_ns"] - late["connect_ns"]) / 1e9 if late["caught_up_ns"] else float("nan")
    return {
        "run": run["id"],
        "lags_ms": lags,
        "frames": sum(v["frames"] for v in live),
        "run_age_s": age,
        "catch_up_s": catch_up,
        "late_frames": late["frames"],
        "late_bytes": late["bytes"],
    }


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--viewer-worker":
        viewer(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="live window per case")
    ap.add_argument("--viewers", type=int, default=5, help="viewers of the N-viewer case")
    ap.add_argument("--build", default="relbot", help="bundled build to run (1 kHz)")
    ap.add_argument("--cpu", type=int, default=1, help="CPU of the loop; stress-ng loads another")
    ap.add_argument("--prio", type=int, default=80)
    ap.add_argument("--edge", type=float, default=1.0, help="a viewer is at the live edge within this lag (s)")
    ap.add_argument(
        "--cases",
        default="browser,1,n,stress",
        help="which of browser, wire, 1, n, stress, footprint (RSS; --watch s)",
    )
    ap.add_argument("--late", type=float, default=60.0, help="browser case: run age when the viewer opens (s)")
    ap.add_argument("--watch", type=float, default=40.0, help="browser case: how long the viewer is sampled (s)")
    ap.add_argument("--viewport", default="1280x800", help="browser case: the viewer's page size, WxH (CSS px)")
    ap.add_argument("--full-size", action="store_true", help="browser case: the live view's canvas as large as the tab")
    ap.add_argument(
        "--all-frames", action="store_true", help="browser case: every frame the viewer asks for (no frames on demand)"
    )
    ap.add_argument(
        "--fresh-profile",
        action="store_true",
        help="browser case: Playwright's off-the-record context (no disk cache) instead of a profile on disk",
    )
    ap.add_argument(
        "--cold",
        action="store_true",
        help="browser case: a profile on disk that has never loaded the viewer (a person's first opening)",
    )
    ap.add_argument(
        "--via-runs-page",
        type=float,
        default=None,
        metavar="S",
        help="browser case: open the viewer as a person does, from the dashboard's Runs page (S s after it was "
        "shown) with its Live plots button; times from the click",
    )
    ap.add_argument(
        "--browser-stress",
        type=int,
        default=0,
        metavar="N",
        help="browser case: N stress-ng CPU workers (unpinned) from the run's start to the end (load)",
    )
    ap.add_argument(
        "--reopen",
        type=float,
        default=0.0,
        metavar="S",
        help="browser case: measure a second opening: the live viewer opened once before (until it drew data), "
        "closed, and nobody watching for S s",
    )
    ap.add_argument("--runs", type=int, default=3, help="wire case: runs (each: its first viewer, then --reopens)")
    ap.add_argument("--reopens", type=int, default=3, help="wire case: openings after the first in each run")
    ap.add_argument("--gap", type=float, default=10.0, help="wire case: s nobody watches between two openings")
    ap.add_argument(
        "--ask-after",
        type=float,
        default=0.7,
        help="wire case: s from the page's request to the stream's (the tab asks once the wasm is compiled)",
    )
    ap.add_argument("--read", type=float, default=3.0, help="wire case: s each opening reads the stream")
    args = ap.parse_args()

    other = next((c for c in range(os.cpu_count() or 1) if c != args.cpu), None)
    cases = []
    browser = "browser" in args.cases.split(",")
    for name in args.cases.split(","):
        if name in ("browser", "footprint", "wire"):
            continue
        if name == "1":
            cases.append(("1 viewer", 1, None))
        elif name == "n":
            cases.append((f"{args.viewers} viewers", args.viewers, None))
        elif name == "stress":
            if shutil.which("stress-ng") and other is not None:
                cases.append((f"1 viewer, CPU {other} loaded", 1, other))
            else:
                print("stress case skipped: needs stress-ng and a second CPU", file=sys.stderr)
    loop_env = {"XRF_PRIO": str(args.prio), "XRF_CPU": str(args.cpu)}
    results = []
    seen = None
    wire_rows: list[tuple[str, float, dict]] = []
    load_before = os.getloadavg()
    with appliance(loop_env=loop_env) as server:
        if "footprint" in args.cases.split(","):
            print(f"RSS (MB) of the appliance and its rerun children, {args.build} at 1 kHz")
            for what, app_mb, kids in footprint_case(server, args.build, args.watch):
                kid = ", ".join(f"rerun --{k} {mb:.0f}" for k, (_, mb) in sorted(kids.items())) or "no rerun child"
                print(f"  {what:36s} appliance {app_mb:.0f}; {kid}", flush=True)
        if "wire" in args.cases.split(","):
            wire_rows = wire_case(
                server,
                args.build,
                args.runs,
                args.reopens,
                args.late,
                args.gap,
                args.ask_after,
                args.read,
                args.browser_stress,
            )
        if browser:
            w, h = (int(x) for x in args.viewport.lower().split("x"))
            seen = browser_case(
                server,
                args.build,
                args.late,
                args.watch,
                args.edge,
                {"width": w, "height": h},
                args.full_size,
                args.all_frames,
                args.fresh_profile,
                args.cold,
                args.reopen,
                args.via_runs_page,
                args.browser_stress,
            )
            print("browser: done", file=sys.stderr)
        for label, n, stress_cpu in cases:
            res = run_case(server, args.build, n, args.seconds, args.edge, stress_cpu)
            results.append((label, res))
            print(f"{label}: done", file=sys.stderr)

    load_after = os.getloadavg()
    print(f"load average (1, 5, 15 min) before: {load_before}, after: {load_after}")
    if wire_rows:
        print(
            f"the stream at the wire, as the tab asks for it ({args.ask_after:g} s after the viewer's page; "
            f"{args.late:g} s into each run, reopened {args.gap:g} s after the last viewer left): the page served "
            "(s after its request), then s after the stream's request"
        )
        print(
            f"{'opening':8s} {'load':>5s} {'page':>6s} {'headers':>8s} {'1st bytes':>9s} {'1st data':>9s} "
            f"{'its age':>8s} {'burst':>6s}"
        )
        for which, load, r in wire_rows:
            print(
                f"{which:8s} {load:5.1f} {r['page_s']:6.3f} {r.get('headers_s', float('nan')):8.3f} "
                f"{r.get('first_bytes_s', float('nan')):9.3f} "
                f"{r.get('first_data_s', float('nan')):9.3f} {r.get('first_data_age_s', float('nan')):8.3f} "
                f"{r.get('burst_newest_age_s', float('nan')):6.3f}"
            )
        for which in ("first", "reopen"):
            got = [r["first_data_s"] for w, _, r in wire_rows if w == which and "first_data_s" in r]
            ages = [r["first_data_age_s"] for w, _, r in wire_rows if w == which and "first_data_age_s" in r]
            if got:
                print(
                    f"  {which}: request -> first data frame p50 {pct(got, 50):.3f} s, max {max(got):.3f} s (n={len(got)}); "
                    f"its newest sample's age p50 {pct(ages, 50):.3f} s, max {max(ages):.3f} s"
                )
    if seen is not None:
        b, e, th = seen["behind"], seen["empty"], seen["thread"]

        def stalls(d: dict) -> str:
            return ", ".join(f"{g:.1f} s at {a:.1f} s" for g, a in d["stalls"]) or "none"

        window = os.environ.get("XRF_RERUN_MEMORY", "the default")
        print(
            f"chromium's rerun viewer, {args.viewport} px, its live canvas {seen['canvas'][0]}x{seen['canvas'][1]} "
            f"px, the live proxy's window {window}"
        )
        print(
            f"  empty viewer (no stream): app started {e['app_start_s']:.1f} s after opening; longest stalls "
            f"of its thread after that: {stalls(e)}; {e['fps_median']} frames/s (median)"
        )
        print(
            f"live viewer opened {seen['run_age_s']:g} s into a {args.build} run"
            + (f", a second time ({args.reopen:g} s after the first closed)" if args.reopen else "")
            + (
                f", from the Runs page's Live plots button ({args.via_runs_page:g} s after the page was shown)"
                if args.via_runs_page is not None
                else ""
            )
            + (f", {args.browser_stress} stress-ng CPU workers running" if args.browser_stress else "")
            + f", load average (1 min) {seen['load_at_open']:.1f} at the opening"
            + " (what a person sees: "
            f"the viewer's newest sample, {seen['samples']} samples of its state)"
        )
        print(
            f"  its thread's longest stalls after the app started: {stalls(th)} (s after opening); "
            f"{th['fps_median']} frames/s (median); {seen['debug_lines']} console.debug lines reached the console"
        )
        print(
            f"  app started {seen['app_start_s']:.1f} s after opening; first held a sample of the run "
            f"{seen['first_s']:.1f} s later, that sample {seen['first_age_s']:.1f} s older than the opening"
        )
        wire = seen["wire"]
        print(
            "  the stream, s after opening: "
            + ", ".join(
                f"{k.removeprefix('stream_').replace('_', ' ')} {v:.1f}"
                for k, v in sorted(wire.items(), key=lambda i: i[1])
            )
        )
        ph = seen["phases"]
        print(
            "  where the time went, s after opening: "
            + ", ".join(
                f"{k} {v:.2f}" for k, v in sorted((i for i in ph.items() if i[0] not in _NOT_TIMES), key=lambda i: i[1])
            )
        )
        if "first_drawn" in ph:
            print(
                f"  first frame holding a sample of the run: {ph['first_drawn']:.2f} s after opening (frame "
                f"{ph['first_drawn_frame']:.0f} of the app), {ph['first_drawn_behind']:.2f} s behind live; the frame "
                f"after it ended {ph.get('next_frame_end', float('nan')):.2f} s after opening, "
                f"{ph.get('next_frame_end_behind', float('nan')):.2f} s behind that sample's time; "
                f"wasm transferred {ph['wasm_transfer_MB']:.1f} MB (0: from the cache); the stream asked for at "
                f"the page's load: {ph['early']}, holding {ph['held']} when the viewer asked"
            )
        if "first_drawn" in ph:
            # one line per run, to gather distributions
            print(
                f"  SUMMARY load {seen['load_at_open']:.1f} app {seen['app_start_s']:.2f} first_drawn "
                f"{ph['first_drawn']:.2f} behind {ph['first_drawn_behind']:.2f} = own frame "
                f"{ph['first_frame_own_s']:.2f} + stale at its start {ph['first_drawn_stale']:.2f} (newest bytes at "
                f"the network {ph.get('net_gap_s', float('nan')):.2f} s before it began); early {ph['early']}, "
                f"held {ph['held']}; the 4 frames before it {ph['frames_before']} s; shader compiles/links in it "
                f"{ph['first_frame_gl']}; warm-up {ph['warmup']}; plots drawn {ph['plots_drawn']:.2f} behind "
                f"{ph['plots_drawn_behind']:.2f}"
            )
        if ph.get("gl_frames"):
            # the frames that compiled shaders (s after the opening + own time: compiles/links): with the
            # warm-up, before the first frame with the run's data (session 14)
            print(f"  SHADERS {ph['gl_frames']}")
        if "timeline" in ph:
            print(f"  TIMELINE {ph['timeline']}")
        print("  behind live " + ", ".join(f"{t} s after start: {v:.1f} s" for t, v in b.items()))
        print(
            f"  within {args.edge:g} s of live {seen['edge_s']:.1f} s after the app started "
            f"({seen['edge_from_open_s']:.1f} s after opening); within it from then on from "
            f"{seen['kept_s']:.1f} s after the app started; worst from 1 s / 5 s after the app started: "
            f"{seen['worst_after'][1]:.1f} / {seen['worst_after'][5]:.1f} s behind"
        )
        fps, cpu = seen["frames_per_s"], seen["cpu_per_s"]
        print(
            f"  while sampled: {fps:.2f} frames/s; CPU (share of one core) gpu-process {cpu.get('gpu-process', 0):.2f}, "
            f"renderers {cpu.get('renderer', 0):.2f}; GPU-process CPU per frame "
            f"{cpu.get('gpu-process', 0) / fps if fps else float('nan'):.2f} s"
        )
        if seen["gate"]:  # frontend/rerun-tab.js: frames on demand in the live tab
            g = seen["gate"]
            print(
                f"  the tab's frame gate over the whole view: {g['drawn']} frames drawn of {g['asked']} the viewer "
                f"asked for; {g['data']} reads of the stream brought data"
            )
    if not results:
        return
    print(
        f"live rerun lag (frame arrival - newest sample in it), {args.build} at 1 kHz, "
        f"{args.seconds:g} s per case, through the appliance's gRPC-web route"
    )
    print(
        f"{'case':24s} {'frames':>7s} {'p50':>8s} {'p99':>8s} {'max':>8s}   late viewer: catch-up (run age, replayed)"
    )
    for label, r in results:
        lags = r["lags_ms"]
        if not lags:
            print(f"{label:24s} no frame with a time reached the viewers")
            continue
        print(
            f"{label:24s} {r['frames']:7d} {pct(lags, 50):6.0f}ms {pct(lags, 99):6.0f}ms {max(lags):6.0f}ms   "
            f"{r['catch_up_s']:.2f} s ({r['run_age_s']:.0f} s, {r['late_frames']} frames, "
            f"{r['late_bytes'] / 1e6:.1f} MB)"
        )


if __name__ == "__main__":
    main()
