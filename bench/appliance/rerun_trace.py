#!/usr/bin/env python3
"""Where the live viewer's first frame with data goes: a Chrome trace of one opening (issue 31 bug 6).

A real appliance, a RELbot run at 1 kHz, Debian's chromium (Playwright, a fresh off-the-record
context: no shader or code cache, as a browser's first opening); the live viewer's page opened
--late s into the run, traced from its opening for --watch s (Chrome's tracing, started for that
page: devtools.timeline, gpu, blink, cc, viz). Printed: the rerun_lag.py marks of the opening (the
first frame holding a sample of the run: its own time and how old its newest sample was at its
start), then the longest animation-frame callback on the page's main thread (the viewer's first
frame with data, in every trace so far) broken down by what it waited for there (synchronous
WebGL calls waiting for the GPU process: compile and link status queries, ...), and what the
other threads did meanwhile (the GPU process's shader compiler workers, the renderer's pool).
--out keeps the trace (open it in chrome://tracing or ui.perfetto.dev). Not a timed test.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import sys
import time
import urllib.parse

from _common import appliance

CATEGORIES = [
    "devtools.timeline",
    "gpu",
    "blink",
    "toplevel",
    "cc",
    "viz",
    "v8",
    "disabled-by-default-devtools.timeline",
]


def breakdown(trace: bytes) -> list[str]:
    """The longest FireAnimationFrame on a renderer main thread (with the tab's warm-up, session 14:
    the warm-up's frame) and the longest after it: their events by total duration, and the other
    threads' events in their time windows."""
    data = json.loads(trace)
    events = data["traceEvents"] if isinstance(data, dict) else data
    names: dict[tuple, str] = {}
    for e in events:
        if e.get("ph") == "M" and e.get("name") in ("thread_name", "process_name"):
            names[(e["pid"], e["tid"] if e["name"] == "thread_name" else None)] = e["args"]["name"]
    frames = [e for e in events if e.get("name") == "FireAnimationFrame" and e.get("ph") == "X"]
    if not frames:
        return ["no animation frame in the trace"]
    longest = max(frames, key=lambda e: e.get("dur", 0))
    after = [e for e in frames if e["ts"] >= longest["ts"] + longest.get("dur", 0)]
    out = _one_frame(events, names, longest, "the longest animation frame callback")
    if after:
        nxt = max(after, key=lambda e: e.get("dur", 0))
        gap = (nxt["ts"] - longest["ts"]) / 1e6
        out += _one_frame(events, names, nxt, f"the longest after it ({gap:.2f} s after its start)")
    return out


def _one_frame(events: list[dict], names: dict[tuple, str], frame: dict, what: str) -> list[str]:
    t0, t1, pid, tid = frame["ts"], frame["ts"] + frame["dur"], frame["pid"], frame["tid"]
    mine: collections.Counter = collections.Counter()
    mine_n: collections.Counter = collections.Counter()
    other: collections.Counter = collections.Counter()
    other_n: collections.Counter = collections.Counter()
    for e in events:
        if e.get("ph") != "X" or e is frame or not t0 <= e.get("ts", 0) <= t1:
            continue
        if e["pid"] == pid and e["tid"] == tid:
            mine[e["name"]] += e.get("dur", 0)
            mine_n[e["name"]] += 1
        else:
            key = f"{names.get((e['pid'], None), e['pid'])} / {names.get((e['pid'], e['tid']), e['tid'])} / {e['name']}"
            other[key] += e.get("dur", 0)
            other_n[key] += 1
    out = [f"{what}: {frame['dur'] / 1e3:.0f} ms; inside it (ms in total, calls):"]
    out += [f"  {v / 1e3:8.1f} {mine_n[k]:5d}  {k}" for k, v in mine.most_common(14)]
    out.append("other threads in that window (ms in total, events):")
    out += [f"  {v / 1e3:8.1f} {other_n[k]:5d}  {k}" for k, v in other.most_common(14)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--late", type=float, default=20.0, help="run age when the viewer opens (s)")
    ap.add_argument("--watch", type=float, default=8.0, help="s traced after the viewer's app started")
    ap.add_argument("--out", default="", help="keep the trace in this file (JSON)")
    args = ap.parse_args()

    from playwright.sync_api import sync_playwright
    from rerun_lag import PHASES, phases, start_loop

    from xrf_testing.harness import CHROMIUM_ARGS, session_cookies

    chromium = os.environ.get("XRF_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        raise SystemExit("needs Debian's chromium (or XRF_CHROMIUM)")
    with appliance(loop_env={"XRF_PRIO": "80", "XRF_CPU": "1"}) as server:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            try:
                ctx = browser.new_context(viewport={"width": 1280, "height": 800})
                ctx.add_cookies(session_cookies(server.http, server.url))
                warm = ctx.new_page()  # the viewer's files prepared by the appliance: not traced
                warm.goto(server.url + "/rerun/index.html", timeout=600_000)
                warm.wait_for_function("() => window._handle !== undefined", timeout=600_000)
                warm.close()
                run = start_loop(server, "relbot")
                started = time.monotonic()
                while time.monotonic() - started < args.late:
                    time.sleep(0.2)  # time passing: the run's age
                info = server.http.get("/api/logs/rerun").json()
                live = server.url + "/rerun/?url=" + urllib.parse.quote(info["live_url"], safe="")
                page = ctx.new_page()
                page.add_init_script(PHASES)
                browser.start_tracing(page=page, categories=CATEGORIES)
                load = os.getloadavg()[0]
                opened_ns = time.time_ns()
                page.goto(live, timeout=120_000)
                page.wait_for_function("() => window._handle !== undefined", timeout=600_000)
                end = time.monotonic() + args.watch
                while time.monotonic() < end:
                    time.sleep(0.5)  # time passing: the viewer draws its first data
                trace = browser.stop_tracing()
                marks = phases(page, opened_ns, f"run-{run['id']}")
            finally:
                browser.close()
                server.stop_run()
    if args.out:
        with open(args.out, "wb") as f:
            f.write(trace)
    print(f"load average (1 min) at the opening {load:.1f}")
    if "first_drawn" in marks:
        print(
            f"first frame holding a sample: {marks['first_drawn_began']:.2f}-{marks['first_drawn']:.2f} s after the "
            f"opening, {marks['first_drawn_behind']:.2f} s behind = own frame {marks['first_frame_own_s']:.2f} + stale "
            f"at its start {marks['first_drawn_stale']:.2f}"
        )
        print(f"  {marks['timeline']}")
        # WebGL shader compiles / program links in that frame, and every frame that compiled (s after
        # the opening + its own time: compiles/links); the tab's warm-up's state (session 14)
        print(
            f"  shader compiles/links in it: {marks['first_frame_gl']}; warm-up {marks['warmup']}; its plots drawn "
            f"(pipelines built) {marks['plots_drawn']:.2f} s after the opening, {marks['plots_drawn_behind']:.2f} s behind"
        )
    if marks.get("gl_frames"):
        print(f"  frames that compiled shaders: {marks['gl_frames']}")
    for line in breakdown(trace):
        print(line)


if __name__ == "__main__":
    sys.exit(main())
