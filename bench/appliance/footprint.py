#!/usr/bin/env python3
"""The appliance's footprint (issue 30 item 4): CPU (% of one core) and memory (RSS, PSS) of the
appliance and of every process it starts (rerun servers, viser, the ROS 2 bridge, the run's
launcher), with a RELbot run in RUN at 1 kHz, in five cases that add up:

    idle       nothing connected (no browser, no WebSocket)
    dash       + one dashboard: a real chromium page (Debian's, via Playwright) on /#watch
    view3d     + the 3D view: the dashboard's 3D page (/#view3d) and the scene's own tab (/viser/,
               viser through the appliance's proxy)
    rerun      + the live rerun viewer: a third page on /rerun/?url=... (its wasm viewer)
    dash30     + 30 dashboards as WebSocket clients (a separate process; the stand-in for 30
               browsers that clients30.py uses)
    after      everything closed again: what stays (helpers kept after their last viewer left)

CPU: utime + stime of each process from /proc/PID/stat over the window (default 20 s), so a
process's threads are all counted; the loop process (the student's controller) is shown but not
added: it is the workload, not the appliance. Memory at the end of each window: VmRSS from
/proc/PID/status, Pss from /proc/PID/smaps_rollup (shared pages split between the processes
that map them, so PSS adds up and RSS double-counts the shared libraries).

Instructions: `perf stat -e instructions` needs a hardware PMU, which this VM does not expose
(perf says <not supported>); the script tries it and says so. A Pi 4 figure is estimated from
the CPU time instead: --calibrate times a fixed pure-Python loop (the appliance's work is
CPython: JSON, asyncio, numpy-free parsing) and prints ns per iteration; run the same command
on a Pi 4 and the ratio of the two is the factor to multiply this machine's % by. Without a Pi
measurement the table uses a stated factor (--pi-factor, default 3.5: a Cortex-A72 at 1.5 GHz
runs single-threaded CPython about 3-4x slower than a 2.5 GHz Xeon core).

    .venv/bin/python bench/appliance/footprint.py [--seconds 20] [--cases idle,dash,...]
    .venv/bin/python bench/appliance/footprint.py --soak-minutes 30   # RSS of each process every minute, idle + one dashboard
    .venv/bin/python bench/appliance/footprint.py --calibrate

Not a test; prints figures. Needs chromium (Debian) and playwright (the test extras).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

from _common import appliance

CASES = ("idle", "dash", "view3d", "rerun", "dash30", "after")
TICKS = os.sysconf("SC_CLK_TCK")


# ---- processes ----------------------------------------------------------------------------------


def _stat(pid: int) -> tuple[int, float] | None:
    """(ppid, cpu seconds) of a process, None when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / TICKS


def descendants(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            st = _stat(int(d))
            if st:
                children.setdefault(st[0], []).append(int(d))
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def role(pid: int, root: int, loop_exe: str | None) -> str:
    """What a process of the appliance's tree is, from its command line."""
    if pid == root:
        return "appliance"
    c = cmdline(pid)
    if "--serve-web" in c:
        return "rerun web server"
    if "--serve-grpc" in c:
        return "rerun live (grpc)"
    if "viser" in c or "xrflab.viz" in c:
        return "viser (3D view)"
    if "ros" in c and ("bridge" in c or "xrflab.ros" in c):
        return "ROS 2 bridge"
    if loop_exe and loop_exe in c:
        return "loop (workload)"
    if "launch" in c or "xrf-run" in c or "sandbox" in c:
        return "run launcher"
    return "other: " + (c[:60] if c else f"pid {pid}")


def memory(pid: int) -> tuple[float, float]:
    """(RSS MB, PSS MB)."""
    rss = pss = 0.0
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                pss = int(line.split()[1]) / 1024
    except OSError:
        pass
    return rss, pss


@dataclass
class Row:
    role: str
    cpu_pct: float = 0.0
    rss: float = 0.0
    pss: float = 0.0
    threads: int = 0
    pids: list[int] = field(default_factory=list)


def threads(pid: int) -> int:
    try:
        return len(os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return 0


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds of each thread of a process, by thread name (threads of one name added)."""
    out: dict[str, float] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            raw = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue
        name = raw[raw.index("(") + 1 : raw.rindex(")")]
        f = raw.rsplit(")", 1)[1].split()
        out[name] = out.get(name, 0.0) + (int(f[11]) + int(f[12])) / TICKS
    return out


LAST_THREADS: dict[str, float] = {}  # the appliance's threads, % of one core, of the last window


def measure(root: int, seconds: float, loop_exe: str | None) -> dict[str, Row]:
    """CPU of every process of the tree over the window (those present at both ends), memory at
    its end, grouped by role; the appliance's own threads into LAST_THREADS."""
    pids0 = descendants(root)
    cpu0 = {p: s[1] for p in pids0 if (s := _stat(p))}
    th0 = thread_cpu(root)
    t0 = time.monotonic()
    time.sleep(seconds)
    cpu1 = {p: s[1] for p in descendants(root) if (s := _stat(p))}
    dt = time.monotonic() - t0
    th1 = thread_cpu(root)
    LAST_THREADS.clear()
    for name, c in th1.items():
        LAST_THREADS[name] = 100 * (c - th0.get(name, 0.0)) / dt
    rows: dict[str, Row] = {}
    for p, c1 in cpu1.items():
        r = rows.setdefault(role(p, root, loop_exe), Row(role(p, root, loop_exe)))
        if p in cpu0:  # started during the window: its CPU is not known from the start
            r.cpu_pct += 100 * (c1 - cpu0[p]) / dt
        rss, pss = memory(p)
        r.rss += rss
        r.pss += pss
        r.threads += threads(p)
        r.pids.append(p)
    return rows


def perf_instructions(pids: list[int], seconds: float) -> str:
    """perf stat -e instructions over the pids, or why not."""
    if not shutil.which("perf"):
        return "perf not installed"
    r = subprocess.run(
        ["perf", "stat", "-x,", "-e", "instructions", "-p", ",".join(map(str, pids)), "sleep", str(seconds)],
        capture_output=True,
        text=True,
    )
    line = next((ln for ln in r.stderr.splitlines() if "instructions" in ln), r.stderr.strip()[-200:])
    value = line.split(",")[0]
    if not value.isdigit():
        return f"not available here ({value or line})"
    return f"{int(value) / seconds / 1e6:.1f} M instructions/s"


# ---- the cases ----------------------------------------------------------------------------------


def calibrate(n: int = 3_000_000) -> float:
    """ns per iteration of a fixed CPython loop (dict, str and int work, like a JSON encoder's)."""
    best = float("inf")
    for _ in range(5):
        d: dict[str, int] = {}
        t = time.perf_counter_ns()
        for i in range(n):
            k = "k" + str(i & 255)
            d[k] = d.get(k, 0) + i
        best = min(best, (time.perf_counter_ns() - t) / n)
    return best


def ws_clients_worker(url: str, ws_url: str, n: int) -> None:
    """n dashboards' WebSockets in a session, reading everything until stdin closes."""
    import asyncio
    import threading

    from websockets.asyncio.client import connect

    from xrf_testing.harness import ADMIN_PASSWORD, ADMIN_USER, login_client

    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    cookie = {"Cookie": f"xrf_session={http.cookies.get('xrf_session')}"}
    http.close()

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        threading.Thread(target=lambda: (sys.stdin.read(), loop.call_soon_threadsafe(stop.set)), daemon=True).start()
        connected = 0

        async def one() -> None:
            nonlocal connected
            async with connect(ws_url, max_size=None, origin=url, additional_headers=cookie) as ws:
                connected += 1
                if connected == n:
                    print("connected", flush=True)
                while not stop.is_set():
                    try:
                        await asyncio.wait_for(ws.recv(), timeout=0.5)
                    except asyncio.TimeoutError:
                        pass

        await asyncio.gather(*(one() for _ in range(n)))

    asyncio.run(main())


def fmt_table(case: str, rows: dict[str, Row], pi_factor: float) -> list[str]:
    app = [r for k, r in rows.items() if k != "loop (workload)"]
    cpu = sum(r.cpu_pct for r in app)
    rss = sum(r.rss for r in app)
    pss = sum(r.pss for r in app)
    out = [
        f"{case}: appliance + helpers {cpu:.2f} % of one core (Pi 4 est. {cpu * pi_factor:.1f} %), RSS {rss:.0f} MB, PSS {pss:.0f} MB"
    ]
    for r in sorted(rows.values(), key=lambda r: -r.rss):
        out.append(
            f"    {r.role:<24} cpu {r.cpu_pct:6.2f} %  rss {r.rss:7.1f} MB  pss {r.pss:7.1f} MB  threads {r.threads:3d}  pids {r.pids}"
        )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="window per case")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--pi-factor", type=float, default=3.5, help="Pi 4 core / this core, for CPU time")
    ap.add_argument("--soak-minutes", type=float, default=0.0, help="idle + one dashboard, RSS every minute")
    ap.add_argument("--calibrate", action="store_true", help="only print this machine's CPython ns/iteration")
    ap.add_argument("--json", help="also write the figures to this file")
    ap.add_argument("--ws-worker", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.ws_worker:
        ws_clients_worker(a.ws_worker[0], a.ws_worker[1], int(a.ws_worker[2]))
        return 0
    if a.calibrate:
        print(f"calibration: {calibrate():.1f} ns per iteration (run the same on the Pi: the ratio is --pi-factor)")
        return 0
    cases = [c for c in a.cases.split(",") if c]
    print(
        f"# appliance footprint  {time.strftime('%Y-%m-%d %H:%M:%S')}  host {os.uname().nodename}  cpus {os.cpu_count()}"
    )
    print(f"# CPython calibration here: {calibrate():.1f} ns/iteration; Pi factor used: {a.pi_factor}")
    from playwright.sync_api import sync_playwright

    from xrf_testing.harness import CHROMIUM_ARGS, session_cookies

    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    results: dict[str, list[dict]] = {}
    with appliance() as server, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        ctx = browser.new_context(viewport={"width": 1400, "height": 1000})
        ctx.add_cookies(session_cookies(server.http, server.url))
        run = server.start_run("relbot")
        for cmd in ("initialise", "start"):
            r = server.http.post("/api/runs/current/command", json={"cmd": cmd})
            assert r.json().get("accepted"), r.text
        loop_exe = run.get("executable") or run.get("program") or "relbot"
        time.sleep(3)  # the run's helpers (live rerun stream, bridge) started
        pages = []
        worker = None
        try:
            for case in cases:
                if case == "dash":
                    pg = ctx.new_page()
                    pg.goto(server.url + "/#watch")
                    pg.wait_for_function("document.getElementById('conn').textContent === 'connected'")
                    pages.append(pg)
                elif case == "view3d":
                    # The 3D page (its numbers poll /api/viz/state) and the scene, which opens in a
                    # tab of its own on /viser/ (frontend/pages/view3d.js: never in an iframe).
                    pg = ctx.new_page()
                    pg.goto(server.url + "/#view3d")
                    pg.wait_for_function("() => window.xrf && window.xrf.view3d", timeout=60_000)
                    pages.append(pg)
                    pg = ctx.new_page()
                    pg.goto(server.url + "/viser/")
                    pg.locator("canvas").first.wait_for(state="attached", timeout=60_000)
                    pages.append(pg)
                elif case == "rerun":
                    pg = ctx.new_page()
                    # The first open prepares the viewer's files (a rerun child, once per version)
                    # and loads ~30 MB of wasm: slow on a busy machine.
                    pg.goto(server.url + "/rerun/?url=" + quote(f"rerun+{server.url}/proxy", safe=""), timeout=240_000)
                    pg.wait_for_function("() => window._handle !== undefined", timeout=240_000)
                    pages.append(pg)
                elif case == "dash30":
                    worker = subprocess.Popen(
                        [sys.executable, __file__, "--ws-worker", server.url, server.ws_url, "30"],
                        stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE,
                        text=True,
                    )
                    assert worker.stdout is not None
                    if "connected" not in worker.stdout.readline():
                        raise SystemExit("the 30 WebSocket clients did not connect")
                elif case == "after":
                    for pg in pages:
                        pg.close()
                    pages.clear()
                    if worker:
                        worker.stdin.close()  # type: ignore[union-attr]
                        worker.wait(30)
                        worker = None
                time.sleep(2)  # settle: page loads and first subscriptions done
                rows = measure(server.proc.pid, a.seconds, loop_exe)
                for line in fmt_table(case, rows, a.pi_factor):
                    print(line, flush=True)
                busy = sorted(LAST_THREADS.items(), key=lambda kv: -kv[1])
                print("    appliance threads: " + ", ".join(f"{n} {c:.2f}" for n, c in busy if c >= 0.05), flush=True)
                results[case] = [r.__dict__ for r in rows.values()]
            app_pids = [
                p for p in descendants(server.proc.pid) if role(p, server.proc.pid, loop_exe) != "loop (workload)"
            ]
            print(f"instructions (perf stat, {len(app_pids)} processes, 5 s): {perf_instructions(app_pids, 5)}")
            if a.soak_minutes > 0:
                pg = ctx.new_page()
                pg.goto(server.url + "/#watch")
                pages.append(pg)
                print(f"soak: one dashboard, {a.soak_minutes} min, RSS MB per role every minute")
                for minute in range(int(a.soak_minutes) + 1):
                    rows = measure(server.proc.pid, 60 if minute else 1, loop_exe)
                    print(
                        f"  t={minute:4d} min  "
                        + "  ".join(f"{r.role} {r.rss:.1f}" for r in sorted(rows.values(), key=lambda r: r.role)),
                        flush=True,
                    )
        finally:
            for pg in pages:
                pg.close()
            if worker:
                worker.kill()
                worker.wait()
            server.stop_run()
            browser.close()
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
