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

CPU: the CPU time of each process over the window (default 20 s): the sum of its threads'
/proc/PID/task/TID/schedstat run times (ns; utime + stime from /proc/PID/stat, in 10 ms ticks,
where schedstat is missing), so a process's threads are all counted; with it the context
switches per second (voluntary + involuntary, /proc/PID/task/TID/status): how often it wakes.
The loop process (the student's controller) is shown but not added: it is the workload, not the
appliance. Memory at the end of each window: VmRSS from
/proc/PID/status, Pss from /proc/PID/smaps_rollup (shared pages split between the processes
that map them, so PSS adds up and RSS double-counts the shared libraries).

Instructions per second, per process, so that a Pi figure does not depend on this machine's
clock: measured by `perf stat -e instructions -p PID` over the window where the machine has a
hardware PMU; where it has none (a VM: perf says <not supported>) estimated as CPU ns x this
core's instructions per ns, measured once at start on a fixed CPython loop (the appliance's work
is CPython: asyncio, cffi, JSON): its instructions per iteration counted exactly by valgrind's
callgrind (two loop lengths, the difference: the interpreter's start-up cancels out) over its
best native ns per iteration. Pi 4 estimate = instructions/s / (--pi-hz 1.5 GHz x --pi-ipc 1.0
instructions per cycle of a Cortex-A72 on CPython: an assumption, on the slow side for a
3-wide out-of-order core; arm64 and x86-64 are taken to need as many instructions for the same
Python). The older estimate, this machine's % x --pi-factor (3.5, the ratio usually quoted for
single-threaded CPython), is printed beside it; --calibrate prints the loop's ns per iteration,
whose ratio between a Pi and this machine replaces both assumptions once a Pi is at hand.

    .venv/bin/python bench/appliance/footprint.py [--seconds 20] [--cases idle,dash,...]
    .venv/bin/python bench/appliance/footprint.py --soak-minutes 30   # RSS of each process every minute, idle + one dashboard
    .venv/bin/python bench/appliance/footprint.py --calibrate       # ns/iteration (and instructions/ns)

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


def task_times(pid: int) -> tuple[float, int, float] | None:
    """(CPU seconds, context switches, CPU seconds in ticks) of a process: its live threads'
    schedstat run time (ns), their voluntary + involuntary switches, and utime + stime of
    /proc/PID/stat (which keeps the time of threads that ended); None when it is gone."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    cpu_ns = switches = 0
    for tid in tids:
        try:
            cpu_ns += int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0])
            for line in Path(f"/proc/{pid}/task/{tid}/status").read_text().splitlines():
                if line.startswith(("voluntary_ctxt_switches:", "nonvoluntary_ctxt_switches:")):
                    switches += int(line.split()[1])
        except (OSError, IndexError, ValueError):
            continue
    st = _stat(pid)
    if st is None:
        return None
    if cpu_ns == 0:  # no schedstat (a kernel without CONFIG_SCHEDSTATS): the ticks
        return st[1], switches, st[1]
    return cpu_ns / 1e9, switches, st[1]


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
    switches_s: float = 0.0  # context switches per second (wake-ups)
    minstr_s: float = 0.0  # M instructions per second (perf, or CPU ns x instructions/ns here)
    minstr_measured: bool = False  # by perf (True) or estimated (False)
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


def measure(root: int, seconds: float, loop_exe: str | None, ipns: float | None = None) -> dict[str, Row]:
    """CPU and wake-ups of every process of the tree over the window (those present at both
    ends), instructions (perf where the machine counts them, else CPU x `ipns`), memory at its
    end, grouped by role; the appliance's own threads into LAST_THREADS."""
    pids0 = descendants(root)
    cpu0 = {p: t for p in pids0 if (t := task_times(p))}
    perf = {p: start_perf(p, seconds) for p in pids0} if PERF_COUNTS else {}
    th0 = thread_cpu(root)
    t0 = time.monotonic()
    time.sleep(seconds)  # the window: time passing is the point
    cpu1 = {p: t for p in descendants(root) if (t := task_times(p))}
    dt = time.monotonic() - t0
    th1 = thread_cpu(root)
    LAST_THREADS.clear()
    for name, c in th1.items():
        LAST_THREADS[name] = 100 * (c - th0.get(name, 0.0)) / dt
    rows: dict[str, Row] = {}
    for p, (c1, s1, k1) in cpu1.items():
        r = rows.setdefault(role(p, root, loop_exe), Row(role(p, root, loop_exe)))
        if p in cpu0:  # started during the window: its CPU is not known from the start
            c0, s0, k0 = cpu0[p]
            used = c1 - c0 if c1 >= c0 else k1 - k0  # a thread ended: its ns left the sum
            r.cpu_pct += 100 * used / dt
            r.switches_s += (s1 - s0) / dt
            counted = finish_perf(perf.get(p), seconds)
            if counted is not None:
                r.minstr_s += counted / 1e6
                r.minstr_measured = True
            elif ipns:
                r.minstr_s += used * 1e9 * ipns / dt / 1e6
        rss, pss = memory(p)
        r.rss += rss
        r.pss += pss
        r.threads += threads(p)
        r.pids.append(p)
    return rows


def perf_counts_instructions() -> str:
    """ "" when `perf stat -e instructions` counts here, else why not."""
    if not shutil.which("perf"):
        return "perf is not installed"
    r = subprocess.run(["perf", "stat", "-x,", "-e", "instructions", "true"], capture_output=True, text=True)
    line = next((ln for ln in r.stderr.splitlines() if "instructions" in ln), r.stderr.strip()[-200:])
    value = line.split(",")[0]
    return "" if value.isdigit() else f"perf stat -e instructions: {value or line}"


PERF_COUNTS = False  # set in main() when perf counts instructions on this machine


def start_perf(pid: int, seconds: float) -> subprocess.Popen:
    return subprocess.Popen(
        ["perf", "stat", "-x,", "-e", "instructions", "-p", str(pid), "sleep", str(seconds)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish_perf(proc: subprocess.Popen | None, seconds: float) -> float | None:
    """Instructions per second perf counted, None without a count."""
    if proc is None:
        return None
    _, err = proc.communicate(timeout=seconds + 30)
    line = next((ln for ln in err.splitlines() if "instructions" in ln), "")
    value = line.split(",")[0]
    return int(value) / seconds if value.isdigit() else None


# ---- the cases ----------------------------------------------------------------------------------


# The calibration loop: dict, str and int work, like a JSON encoder's. One source for the native
# timing and for callgrind's count, so both measure the same code.
CALIBRATION = """
def loop(n):
    d = {}
    for i in range(n):
        k = "k" + str(i & 255)
        d[k] = d.get(k, 0) + i
"""


def calibrate(n: int = 3_000_000) -> float:
    """Best-of-5 ns per iteration of the calibration loop, natively, in the thread's CPU time
    (time another process took the core is not counted: this is a shared machine)."""
    space: dict = {}
    exec(CALIBRATION, space)
    best = float("inf")
    for _ in range(5):
        t = time.thread_time_ns()
        space["loop"](n)
        best = min(best, (time.thread_time_ns() - t) / n)
    return best


def instructions_per_iteration(short: int = 20_000, long: int = 120_000) -> float | None:
    """The calibration loop's instructions per iteration, counted by callgrind: two runs of
    different lengths, the difference (the interpreter's start and exit cancel out). None
    without valgrind."""
    if not shutil.which("valgrind"):
        return None
    counts = []
    for n in (short, long):
        r = subprocess.run(
            ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null"]
            + [sys.executable, "-I", "-S", "-c", CALIBRATION + f"\nloop({n})\n"],
            capture_output=True,
            text=True,
            timeout=600,
        )
        got = [ln.rsplit(":", 1)[1] for ln in r.stderr.splitlines() if "Collected :" in ln]
        if not got:
            return None
        counts.append(int(got[-1].strip()))
    return (counts[1] - counts[0]) / (long - short)


def instructions_per_ns() -> tuple[float | None, str]:
    """This core's instructions per ns on CPython, and how that was found."""
    per_iter = instructions_per_iteration()
    if per_iter is None:
        return None, "no valgrind: instructions not estimated"
    ns = calibrate()
    return per_iter / ns, (
        f"callgrind: {per_iter:.0f} instructions/iteration of the calibration loop, "
        f"{ns:.1f} ns/iteration natively (best of 5): {per_iter / ns:.2f} instructions/ns"
    )


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


def fmt_table(case: str, rows: dict[str, Row], pi_factor: float, pi_ips: float) -> list[str]:
    app = [r for k, r in rows.items() if k != "loop (workload)"]
    cpu = sum(r.cpu_pct for r in app)
    rss = sum(r.rss for r in app)
    pss = sum(r.pss for r in app)
    minstr = sum(r.minstr_s for r in app)
    how = "perf" if any(r.minstr_measured for r in app) else "est."
    pi = f"Pi 4 est. {100 * minstr * 1e6 / pi_ips:.2f} % by instructions, {cpu * pi_factor:.2f} % by x{pi_factor}"
    out = [
        f"{case}: appliance + helpers {cpu:.3f} % of one core, {sum(r.switches_s for r in app):.0f} switches/s, "
        f"{minstr:.1f} M instructions/s ({how}); {pi}; RSS {rss:.0f} MB, PSS {pss:.0f} MB"
    ]
    for r in sorted(rows.values(), key=lambda r: -r.rss):
        out.append(
            f"    {r.role:<24} cpu {r.cpu_pct:6.3f} %  {r.switches_s:6.1f} sw/s  {r.minstr_s:7.2f} M instr/s  "
            f"rss {r.rss:7.1f} MB  pss {r.pss:7.1f} MB  threads {r.threads:3d}  pids {r.pids}"
        )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="window per case")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--pi-factor", type=float, default=3.5, help="Pi 4 core / this core, for CPU time")
    ap.add_argument("--pi-hz", type=float, default=1.5e9, help="the Pi 4's clock (1.5 GHz; 1.8 GHz on later boards)")
    ap.add_argument("--pi-ipc", type=float, default=1.0, help="Cortex-A72 instructions per cycle on CPython (assumed)")
    # --calibrate on a Pi prints its instructions/ns: that is --pi-hz x --pi-ipc / 1e9.
    ap.add_argument("--ipns", type=float, help="this core's instructions per ns (skips the callgrind calibration)")
    ap.add_argument("--soak-minutes", type=float, default=0.0, help="idle + one dashboard, RSS every minute")
    ap.add_argument("--calibrate", action="store_true", help="only print this machine's CPython ns/iteration")
    ap.add_argument("--json", help="also write the figures to this file")
    ap.add_argument(
        "--task-cpu",
        metavar="PREFIX",
        help="also time the appliance's event loop per asyncio task (bench/appliance/task_cpu/): "
        "snapshots in PREFIX.<pid>, read with task_cpu_report.py",
    )
    ap.add_argument("--ws-worker", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.ws_worker:
        ws_clients_worker(a.ws_worker[0], a.ws_worker[1], int(a.ws_worker[2]))
        return 0
    global PERF_COUNTS
    if a.calibrate:
        print(f"calibration: {calibrate():.1f} ns per iteration (run the same on the Pi: the ratio is --pi-factor)")
        print(f"instructions: {instructions_per_ns()[1]}")
        return 0
    cases = [c for c in a.cases.split(",") if c]
    print(
        f"# appliance footprint  {time.strftime('%Y-%m-%d %H:%M:%S')}  host {os.uname().nodename}  cpus {os.cpu_count()}"
    )
    print(f"# CPython calibration here: {calibrate():.1f} ns/iteration; Pi factor used: {a.pi_factor}")
    why_not = perf_counts_instructions()
    PERF_COUNTS = not why_not
    ipns = a.ipns
    if PERF_COUNTS:
        print("# instructions: counted by perf stat per process")
    else:
        how = f"--ipns {ipns}" if ipns else ""
        if not ipns:
            ipns, how = instructions_per_ns()
        print(f"# instructions: {why_not}; estimated as CPU ns x {ipns or 0:.2f} instructions/ns ({how})")
    pi_ips = a.pi_hz * a.pi_ipc
    print(
        f"# Pi 4 estimate: instructions/s / {pi_ips / 1e9:.2f} G instructions/s (--pi-hz x --pi-ipc), and CPU % x {a.pi_factor}"
    )
    from playwright.sync_api import sync_playwright

    from xrf_testing.harness import CHROMIUM_ARGS, session_cookies

    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    results: dict[str, list[dict]] = {}
    env = None
    if a.task_cpu:
        # After the harness's own path (start_server): the timer's folder, its sitecustomize.
        env = {"PYTHONPATH": str(Path(__file__).resolve().parent / "task_cpu"), "XRF_TASK_CPU_OUT": a.task_cpu}
    with appliance(env=env) as server, sync_playwright() as p:
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
                rows = measure(server.proc.pid, a.seconds, loop_exe, ipns)
                for line in fmt_table(case, rows, a.pi_factor, pi_ips):
                    print(line, flush=True)
                print("    load average (1, 5, 15 min): " + ", ".join(f"{x:.2f}" for x in os.getloadavg()))
                busy = sorted(LAST_THREADS.items(), key=lambda kv: -kv[1])
                print("    appliance threads: " + ", ".join(f"{n} {c:.2f}" for n, c in busy if c >= 0.05), flush=True)
                results[case] = [r.__dict__ for r in rows.values()]
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
        # The run's record: every cycle in RUN logged, none lost (the cuts must not cost a sample).
        row = server.http.get(f"/api/runs/{run['id']}").json()
        print(f"run log: {row.get('log_records')} records, {row.get('log_lost')} lost, {row.get('cycles')} cycles")
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
