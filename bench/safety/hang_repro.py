#!/usr/bin/env python3
"""Hangs under load: many short runs, how many end `hang`, and what the hang diagnosis says.

The 4-hour practical (bench/appliance/practical.py) ended 6 of 42 RELbot/Jiwy/youBot runs
`hang` with no steal time on the loop's CPU. This replays its loop (the bundled builds, RUN,
SCHED_FIFO --prio on the last CPU, 1 kHz) in short runs under a load of one kind:

- ``none``: whatever the machine is doing anyway;
- ``stress``: ``stress-ng --cpu N --vm 1 --io 1`` on every CPU (normal priority: the CPU, memory
  and I/O load of builds and downloads);
- ``rt-neighbour``: another program's real-time thread on the loop's CPU, as another appliance's
  hang test makes one (tests/sandbox/test_limits.py's spinners, a hang fixture's busy loop): every
  --neighbour-every seconds a process spins at SCHED_FIFO 99 on that CPU for --neighbour-ms.

Beside the runs, ``stall_probe`` (stall_probe.c, built here with cc) sleeps to a 1 ms grid at
SCHED_FIFO prio-1 on the same CPU and counts wake-ups later than 50 ms: a stall of the CPU itself
(the machine, another program) shows there too, one of our loop alone (blocked, spinning) does not.
For each run that ends `hang` the run's end note (the hang diagnosis, docs/developers/safety.md) is
printed. Root (real-time priorities). Not a test: prints figures.

    .venv/bin/python bench/safety/hang_repro.py --runs 12 --seconds 20 --load stress
    .venv/bin/python bench/safety/hang_repro.py --runs 4 --seconds 10 --load rt-neighbour
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "tests"))

from xrf_testing.harness import shared_builds_root, start_server, stop_server, wait_for  # noqa: E402


def build_probe(out: Path) -> Path:
    exe = out / "stall_probe"
    subprocess.run(["cc", "-O2", "-o", str(exe), str(Path(__file__).with_name("stall_probe.c"))], check=True)
    return exe


def neighbour(cpu: int, every_s: float, spin_ms: float, seconds: float) -> subprocess.Popen:
    """A process that spins at SCHED_FIFO 99 on `cpu` for spin_ms every every_s seconds."""
    code = f"""
import os, time
os.sched_setaffinity(0, {{{cpu}}})
end = time.monotonic() + {seconds}
while time.monotonic() < end:
    time.sleep({every_s})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(99))
    t = time.monotonic() + {spin_ms} / 1000
    while time.monotonic() < t:
        pass
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    print("spun", flush=True)
"""
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=20.0, help="RUN per run")
    ap.add_argument("--builds", default="relbot,jiwy,youbot", help="bundled builds, in turn")
    ap.add_argument("--load", choices=("none", "stress", "rt-neighbour"), default="stress")
    ap.add_argument("--prio", type=int, default=80, help="the loop's SCHED_FIFO priority (XRF_PRIO)")
    ap.add_argument("--neighbour-every", type=float, default=8.0)
    ap.add_argument("--neighbour-ms", type=float, default=250.0)
    ap.add_argument("--json", help="also write the runs' records here")
    a = ap.parse_args()
    cpu = (os.cpu_count() or 1) - 1
    builds = [b for b in a.builds.split(",") if b]
    load0 = os.getloadavg()
    print(
        f"# hang_repro {time.strftime('%Y-%m-%d %H:%M:%S')}  cpus {os.cpu_count()}  load {', '.join(f'{x:.2f}' for x in load0)}"
        f"  runs {a.runs} x {a.seconds:.0f} s  load {a.load}  loop SCHED_FIFO {a.prio} on CPU {cpu}"
    )
    tmp = Path(tempfile.mkdtemp(prefix="xrf-hang-repro-"))
    procs: list[subprocess.Popen] = []
    server = None
    rows = []
    try:
        probe = build_probe(tmp)
        total = a.runs * (a.seconds + 15) + 60
        procs.append(
            subprocess.Popen(
                [str(probe), str(cpu), str(max(1, a.prio - 1)), "50", str(int(total))],
                stdout=subprocess.PIPE,
                text=True,
            )
        )
        server = start_server(
            tmp / "data", shared_builds_root(), loop_env={"XRF_PRIO": str(a.prio), "XRF_CPU": str(cpu)}
        )
        if a.load == "stress":
            if not shutil.which("stress-ng"):
                raise SystemExit("stress-ng is not installed")
            n = os.cpu_count() or 1
            procs.append(
                subprocess.Popen(
                    [
                        "stress-ng",
                        "--cpu",
                        str(n),
                        "--vm",
                        "1",
                        "--vm-bytes",
                        "256M",
                        "--io",
                        "1",
                        "--timeout",
                        f"{int(total)}s",
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        elif a.load == "rt-neighbour":
            procs.append(neighbour(cpu, a.neighbour_every, a.neighbour_ms, total))
        for i in range(a.runs):
            build = builds[i % len(builds)]
            server.stop_run()
            run = server.start_run(build)
            with server.ws() as ws:
                try:  # to RUN as a student does it (the youBot's INITIALISING takes a while under load)
                    ws.wait_state("IDLE", 60)
                    for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
                        assert ws.command(cmd, timeout=30)["accepted"]
                        ws.wait_state(state, 60)
                except AssertionError as exc:
                    print(f"    run {i + 1}: not in RUN ({str(exc)[:120]})", flush=True)
                end = time.monotonic() + a.seconds
                while time.monotonic() < end:
                    row = server.http.get(f"/api/runs/{run['id']}").json()
                    if row["status"] != "running":
                        break
                    time.sleep(0.5)
            server.stop_run()
            row = wait_for(
                lambda rid=run["id"]: (r := server.http.get(f"/api/runs/{rid}").json())["status"] != "running" and r,
                30,
                "the run's end",
            )
            rows.append({k: row.get(k) for k in ("id", "end_reason", "cycles", "misses", "message")} | {"build": build})
            print(
                f"run {i + 1:3d} {build:7s} end {row['end_reason']:8s} cycles {row['cycles']:7d} misses {row['misses']:5d}"
                f"  load {os.getloadavg()[0]:.2f}",
                flush=True,
            )
            if row["end_reason"] == "hang":
                print(f"    {row['message']}", flush=True)
    finally:
        if server is not None:
            server.stop_run()
            stop_server(server)
        for p in procs[1:]:
            p.terminate()
        probe_out = ""
        if procs:
            procs[0].terminate()
            probe_out = procs[0].communicate(timeout=10)[0]
        for p in procs[1:]:
            p.wait(timeout=10)
        shutil.rmtree(tmp, ignore_errors=True)
    hangs = [r for r in rows if r["end_reason"] == "hang"]
    stalls = re.findall(r"STALL cpu \d+ late ([\d.]+) ms", probe_out)
    print(
        f"# {len(rows)} runs, {len(hangs)} hang; probe on CPU {cpu}: {len(stalls)} stalls > 50 ms"
        + (f" ({', '.join(stalls[:10])} ms)" if stalls else "")
        + f"; load {', '.join(f'{x:.2f}' for x in os.getloadavg())}"
    )
    for h in hangs:
        m = re.search(r"hang diagnosis: (.*?) \(hang-diagnosis", h["message"] or "")
        print(f"#   run {h['id']} ({h['build']}): {m.group(1) if m else h['message']}")
    if a.json:
        Path(a.json).write_text(json.dumps({"runs": rows, "probe": probe_out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
