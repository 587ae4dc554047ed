"""Soak: a long run under everything a lab bench goes through, and the safety reaction to crashes.

One appliance (the test harness's: uvicorn in its own process, real loop processes in the run
sandbox). For --minutes: the logger-cost controller (bench/logs/logger_cost_project, on the
simulated RELbot) at 1 kHz logging 32 doubles every cycle, live rerun on, 30 browser-like
WebSocket clients and a 3D-view (viser) client connected through the appliance, a student build
every --build-every seconds, stress-ng on every core, and cyclictest at the loop's priority on
the other CPU in the same window. --crashes times, spread over the window, the controller is
killed (kill -9) mid-RUN; the safety reaction is the time from the kill to the outputs being safe
as the safety watcher recorded it (the alarm's safe_ns, CLOCK_MONOTONIC); a new run follows.

Reports: log records lost (sum over runs), deadline misses of the loop vs. cyclictest's wake-ups
later than one period, appliance RSS at start and end, the crash reactions (p50/p99/max), and the
appliance's descriptors and processes at the end vs. the start.

--arm: the controller is the youBot example on the simulated youBot (safe reaction `hold`), its
arm raised to the ready pose in RUN before each crash; each crash is then also measured by what
the safety watcher did for the arm (the run record's safe_outcome: the largest joint drop and the
time to rest, docs/developers/safety.md), against the 2° bound.

    .venv/bin/python bench/safety/soak.py --minutes 60      # the full soak (an hour)
    .venv/bin/python bench/safety/soak.py --minutes 3 --crashes 6   # a quick look
    .venv/bin/python bench/safety/soak.py --minutes 20 --crashes 20 --arm   # the arm under every load
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "bench" / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "tests"))

from _common import pct  # noqa: E402

from xrf_testing.arm import DROP_BOUND, raise_example  # noqa: E402
from xrf_testing.harness import (  # noqa: E402
    Server,
    WsClient,
    shared_builds_root,
    start_server,
    stop_server,
    wait_for,
    ws_connect,
)
from xrf_testing.leaks import descendants  # noqa: E402
from xrf_testing.logs_support import COST, start  # noqa: E402


def rss_kb(pid: int) -> int:
    m = re.search(r"^VmRSS:\s+(\d+)", Path(f"/proc/{pid}/status").read_text(), re.M)
    return int(m.group(1)) if m else 0


def fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def drive(server: Server, ws: WsClient, arm: bool = False) -> dict[str, Any]:
    if arm:  # the youBot example, its arm raised to the ready pose in RUN
        run, ch = raise_example(server)
        ch.close()
        return run
    run = server.start_run(COST)
    assert ws.command("initialise", timeout=20)["accepted"]
    ws.wait_state("INITIALISED", timeout=20)
    assert ws.command("start", timeout=20)["accepted"]
    ws.wait_state("RUN", timeout=20)
    return run


class Drainers:
    """N dashboards (and the 3D view) that read everything the appliance sends them."""

    def __init__(self, server: Server, n: int) -> None:
        self.stop = threading.Event()
        self.clients = [server.ws() for _ in range(n)]
        try:
            import viser  # the 3D view's own client names its version in the subprotocol

            self.clients.append(
                ws_connect(
                    server.url.replace("http", "ws", 1) + "/viser",
                    server.http,
                    subprotocols=[f"viser-v{viser.__version__}"],
                )
            )
            self.viser = True
        except Exception as exc:  # reported, not fatal: the rest of the soak still means something
            print(f"3D view client not connected: {exc}", file=sys.stderr)
            self.viser = False
        self.received = [0] * len(self.clients)
        self.threads = [threading.Thread(target=self._drain, args=(i,), daemon=True) for i in range(len(self.clients))]
        for t in self.threads:
            t.start()

    def _drain(self, i: int) -> None:
        conn = self.clients[i].conn
        while not self.stop.is_set():
            try:
                conn.recv(timeout=0.5)
                self.received[i] += 1
            except TimeoutError:
                continue
            except Exception:
                return

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2)
        for c in self.clients:
            c.close()


def cyclictest(seconds: int, prio: int, cpu: int) -> subprocess.Popen[str] | None:
    exe = shutil.which("cyclictest")
    if not exe:
        return None
    return subprocess.Popen(
        [exe, "-m", "-p", str(prio), "-a", str(cpu), "-t", "1", "-i", "1000", "-D", f"{seconds}s", "-h", "10000", "-q"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def cyclictest_result(proc: subprocess.Popen[str]) -> dict[str, float]:
    out, _ = proc.communicate()
    buckets = [(int(a), int(b)) for a, b in re.findall(r"^(\d{6})\s+(\d+)", out, re.M)]
    over = sum(n for us, n in buckets if us >= 1000)  # a wake-up a whole period late
    total = sum(n for _, n in buckets)
    mx = re.search(r"# Max Latencies:\s+(\d+)", out)
    return {"samples": total, "late_1ms": over, "max_us": int(mx.group(1)) if mx else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60)
    ap.add_argument("--crashes", type=int, default=20)
    ap.add_argument("--clients", type=int, default=30)
    ap.add_argument("--build-every", type=float, default=300.0)
    ap.add_argument("--prio", type=int, default=80)
    ap.add_argument(
        "--arm", action="store_true", help="the youBot example (hold) instead of the logger-cost controller"
    )
    args = ap.parse_args()
    seconds = args.minutes * 60
    cpus = os.cpu_count() or 2
    loop_cpu, other_cpu = (1, 0) if cpus > 1 else (0, 0)

    with tempfile.TemporaryDirectory(prefix="xrf-soak-") as tmp:
        loop_env = {"XRF_CPU": str(loop_cpu), "XRF_PRIO": str(args.prio), "XRF_BENCH_NVARS": "32"}
        if args.arm:  # the bundled examples (the youBot's), not the logging benchmark's projects
            server = start_server(Path(tmp) / "data", shared_builds_root(), loop_env=loop_env)
        else:
            server = start(Path(tmp) / "data", loop_env=loop_env)
        stress = subprocess.Popen(
            ["stress-ng", "--cpu", str(cpus), "--timeout", f"{int(seconds) + 120}s", "--quiet"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        project = Path(tmp) / "jiwy"
        shutil.copytree(REPO_ROOT / "student_projects/examples/jiwy", project, ignore=shutil.ignore_patterns("build"))
        builds: list[float] = []
        reactions: list[int] = []
        holds: list[dict[str, Any]] = []  # --arm: each crash's safe_outcome
        runs: list[int] = []
        drainers = None
        try:
            with server.ws() as ws:
                run = drive(server, ws, args.arm)
            runs.append(run["id"])
            if True:  # (the block keeps the structure of the steps below readable)
                drainers = Drainers(server, args.clients)
                time.sleep(2)
                pid = server.proc.pid
                start_rss, start_fds, start_procs = rss_kb(pid), fds(pid), len(descendants(pid))
                ct = cyclictest(int(seconds), args.prio, other_cpu)
                t_start = time.monotonic()
                next_build = t_start
                crash_at = [t_start + seconds * (i + 0.5) / args.crashes for i in range(args.crashes)]
                while time.monotonic() - t_start < seconds:
                    now = time.monotonic()
                    if now >= next_build:
                        shutil.rmtree(project / "build", ignore_errors=True)
                        b0 = time.monotonic()
                        subprocess.run(
                            ["nice", "-n", "19", sys.executable, "-m", "xrflab.cli", "build", str(project)],
                            env=dict(os.environ, PYTHONPATH=str(REPO_ROOT / "appliance")),
                            stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL,
                        )
                        builds.append(time.monotonic() - b0)
                        next_build += args.build_every
                    if crash_at and now >= crash_at[0]:
                        crash_at.pop(0)
                        # A fresh dashboard for the alarm: one left unread would be dropped as slow.
                        with server.ws() as ws:
                            t_kill = time.monotonic_ns()
                            os.kill(run["pid"], signal.SIGKILL)
                            alarm = ws.wait_for(
                                lambda m, run_id=run["id"]: (
                                    m.get("type") == "alarm" and m.get("run_id") == run_id and m.get("kind") == "crash"
                                ),
                                timeout=30,
                            )
                            reactions.append(alarm["safe_ns"] - t_kill)
                            if args.arm:  # the run record, once the arm is at rest
                                rid = run["id"]
                                row = wait_for(
                                    lambda rid=rid: (
                                        (r := server.http.get(f"/api/runs/{rid}").json())["end_reason"] and r
                                    ),
                                    30,
                                    "the arm at rest",
                                )
                                holds.append(row.get("safe_outcome") or {})
                            run = drive(server, ws, args.arm)
                        runs.append(run["id"])
                        continue
                    time.sleep(0.2)
                end_rss, end_fds, end_procs = rss_kb(pid), fds(pid), len(descendants(pid))  # a run live, as at start
                server.stop_run()
            lost = 0
            records = 0
            misses = 0
            for rid in runs:
                r = server.http.get(f"/api/logs/runs/{rid}").json()["run"]
                lost += r["log_lost"]
                records += r["log_records"]
                misses += r["misses"]
            ctr = cyclictest_result(ct) if ct else None
        finally:
            if drainers is not None:
                drainers.close()
            os.killpg(stress.pid, signal.SIGKILL)
            stress.wait()
            stop_server(server)

    print(
        f"soak: {args.minutes:g} min, loop 1 kHz SCHED_FIFO {args.prio} on CPU {loop_cpu}, "
        f"{'the youBot example (hold)' if args.arm else '32 doubles logged per cycle'}, live rerun, "
        f"{args.clients} WebSocket clients + 3D view ({'connected' if drainers and drainers.viser else 'NOT connected'}), "
        f"stress-ng on {cpus} CPUs, a build every {args.build_every:g} s ({len(builds)} builds, "
        f"{pct(builds, 50):.1f} s each)"
    )
    print(f"log records: {records} written, {lost} lost over {len(runs)} runs")
    print(
        f"deadline misses: loop {misses}; cyclictest (same window, CPU {other_cpu}): "
        + (
            f"{ctr['late_1ms']} wake-ups >= 1 ms late of {ctr['samples']}, max {ctr['max_us']} us"
            if ctr
            else "not installed"
        )
    )
    print(
        f"appliance RSS: {start_rss / 1024:.1f} MB at start, {end_rss / 1024:.1f} MB at end "
        f"({(end_rss - start_rss) / start_rss * 100:+.1f} %)"
    )
    ms = [r / 1e6 for r in reactions]
    if ms:
        print(
            f"safety reaction, kill -9 -> outputs safe ({len(ms)} crashes): p50 {pct(ms, 50):.2f} ms, "
            f"p99 {pct(ms, 99):.2f} ms, max {max(ms):.2f} ms"
        )
    if args.arm:
        drops = [h["drop_deg"] for h in holds if h.get("phase") == "rest"]
        rests = [h["rest_s"] for h in holds if h.get("phase") == "rest" and h.get("rest_s") is not None]
        print(
            f"arm (hold): {len(drops)} of {len(holds)} crashes ended at rest; largest joint drop p50 "
            f"{pct(drops, 50):.2f}°, max {max(drops, default=float('nan')):.2f}° (bound {math.degrees(DROP_BOUND):.1f}°); "
            f"time to rest p50 {pct(rests, 50):.2f} s, max {max(rests, default=float('nan')):.2f} s"
        )
    print(
        f"appliance descriptors: {start_fds} at start, {end_fds} at end; processes below it: "
        f"{start_procs} at start, {end_procs} at end (both with a run live)"
    )


if __name__ == "__main__":
    main()
