#!/usr/bin/env python3
"""30 browsers at once: appliance CPU, telemetry delivered, and the loop's wake-up jitter with
and without the clients, against cyclictest on the same machine, period, priority and CPU.

Slices alternate (rounds x [loop alone, loop + N clients, cyclictest]), each a fresh RELbot run
in RUN at 1 kHz (XRF_PRIO/XRF_CPU set), so all three sample the same background noise of this
shared machine without running at the same time. Loop jitter is the delta of its shared-memory
WAKEUP histogram over the slice (read by this script, which disturbs nothing); cyclictest's comes
from its own histogram (-h). Percentiles are bucket lower edges (loop: 6 % buckets; cyclictest:
1 us buckets). The N clients run in a separate process (a stand-in for N browsers; on a 2-CPU
machine they compete with the appliance and the loop for CPU, as real browsers on the Pi would not).

Not a timed test; prints figures. Run as root for SCHED_FIFO (else the loop says so, and the
figures say little).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import shutil
import subprocess
import sys
import time

from _common import appliance, cpu_seconds, pct

from xrflab.channels import Channels

# ---- the clients (own process) ------------------------------------------------------------------


async def _clients(url: str, ws_url: str, n: int, seconds: float) -> None:
    from websockets.asyncio.client import connect

    from xrf_testing.harness import ADMIN_PASSWORD, ADMIN_USER, login_client

    # In a session, as a browser is: /ws refuses a connection without a session cookie (before,
    # every client was refused at once and the "with clients" slices had no clients at all).
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    cookie = {"Cookie": f"xrf_session={http.cookies.get('xrf_session')}"}
    http.close()
    counts = [0] * n
    connected = 0
    all_in = asyncio.Event()

    async def one(i: int) -> None:
        nonlocal connected
        async with connect(ws_url, max_size=None, origin=url, additional_headers=cookie) as ws:
            connected += 1
            if connected == n:
                print(json.dumps({"connected": n}), flush=True)
                all_in.set()
            await all_in.wait()
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                try:
                    raw = await asyncio.wait_for(ws.recv(), timeout=max(0.01, end - time.monotonic()))
                except asyncio.TimeoutError:
                    break
                if '"telemetry"' in raw[:40]:
                    counts[i] += 1

    await asyncio.gather(*(one(i) for i in range(n)))
    print(json.dumps({"telemetry_per_client": counts}), flush=True)


# ---- slices -------------------------------------------------------------------------------------


def hist_delta(before: dict[int, int], after: dict[int, int]) -> list[tuple[int, int]]:
    return sorted((edge, after[edge] - before.get(edge, 0)) for edge in after if after[edge] - before.get(edge, 0) > 0)


def hist_pct(buckets: list[tuple[int, int]], p: float) -> float:
    total = sum(n for _, n in buckets)
    seen = 0
    for edge, n in buckets:
        seen += n
        if seen >= p / 100 * total:
            return edge
    return float("nan")


def wakeup(ch: Channels) -> dict[int, int]:
    h = ch.histograms()["wakeup"]
    return dict(zip(h.edges, h.counts))


def loop_slice(server, seconds: float, clients: int) -> dict:
    run = server.start_run("relbot")
    ch = Channels.open(run["shm"], wait_s=5)
    with server.ws() as ws:
        ws.command("initialise")
        ws.wait_state("INITIALISED")
        ws.command("start")
        ws.wait_state("RUN")
    time.sleep(0.3)
    worker = None
    if clients:
        worker = subprocess.Popen(
            [sys.executable, __file__, "--clients-worker", server.url, server.ws_url, str(clients), str(seconds)],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert worker.stdout is not None
        if "connected" not in worker.stdout.readline():  # all logged in and connected
            raise SystemExit("the clients did not connect")
    before, missed0 = wakeup(ch), ch.status().missed
    cpu0, t0 = cpu_seconds(server.proc.pid), time.monotonic()
    time.sleep(seconds)
    after, missed1 = wakeup(ch), ch.status().missed
    cpu1, t1 = cpu_seconds(server.proc.pid), time.monotonic()
    delivered = None
    if worker:
        out, _ = worker.communicate(timeout=seconds + 30)
        delivered = json.loads(out.strip().splitlines()[-1])["telemetry_per_client"]
    server.stop_run()
    ch.close()
    d = hist_delta(before, after)
    return {
        "p50": hist_pct(d, 50),
        "p99": hist_pct(d, 99),
        "max": d[-1][0] if d else float("nan"),
        "cycles": sum(n for _, n in d),
        "missed": missed1 - missed0,
        "cpu_per_s": (cpu1 - cpu0) / (t1 - t0),
        "delivered": delivered,
        "seconds": seconds,
    }


def cyclictest_slice(seconds: float, prio: int, cpu: int) -> dict | None:
    exe = shutil.which("cyclictest")
    if not exe:
        return None
    out = subprocess.run(
        [
            exe,
            "-m",
            "-p",
            str(prio),
            "-a",
            str(cpu),
            "-t",
            "1",
            "-i",
            "1000",
            "-D",
            f"{int(seconds)}s",
            "-h",
            "2000",
            "-q",
        ],
        capture_output=True,
        text=True,
    )
    buckets = [(int(a) * 1000, int(b)) for a, b in re.findall(r"^(\d{6})\s+(\d+)", out.stdout, re.M) if int(b)]
    mx = re.search(r"# Max Latencies:\s+(\d+)", out.stdout)
    if not buckets:
        print("cyclictest gave no histogram:", out.stderr.strip()[:200])
        return None
    return {
        "p50": hist_pct(buckets, 50),
        "p99": hist_pct(buckets, 99),
        "max": int(mx.group(1)) * 1000 if mx else buckets[-1][0],
    }


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--clients-worker":
        asyncio.run(_clients(sys.argv[2], sys.argv[3], int(sys.argv[4]), float(sys.argv[5])))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=8.0, help="per slice")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--prio", type=int, default=80)
    ap.add_argument("--cpu", type=int, default=1)
    args = ap.parse_args()

    loop_env = {"XRF_PRIO": str(args.prio), "XRF_CPU": str(args.cpu)}
    results: dict[str, list[dict]] = {"alone": [], "clients": [], "cyclictest": []}
    with appliance(loop_env=loop_env) as server:
        for r in range(args.rounds):
            order = ["alone", "clients", "cyclictest"] if r % 2 == 0 else ["cyclictest", "clients", "alone"]
            for kind in order:
                if kind == "cyclictest":
                    res = cyclictest_slice(args.seconds, args.prio, args.cpu)
                    if res:
                        results[kind].append(res)
                else:
                    results[kind].append(loop_slice(server, args.seconds, args.clients if kind == "clients" else 0))
                print(f"round {r + 1} {kind}: done", file=sys.stderr)

    def agg(rows: list[dict], key: str, how=pct) -> float:
        vals = [row[key] for row in rows]
        return how(vals, 50) if vals else float("nan")

    print(
        f"{args.clients} WebSocket clients, {args.rounds} x {args.seconds:g} s slices per case, "
        f"loop 1 kHz SCHED_FIFO {args.prio} on CPU {args.cpu}; median over slices"
    )
    print(f"{'case':22s} {'jitter p50':>11s} {'p99':>9s} {'max':>9s} {'missed':>7s} {'appliance CPU':>14s}")
    for kind, label in (
        ("alone", "loop, no clients"),
        ("clients", f"loop + {args.clients} clients"),
        ("cyclictest", "cyclictest"),
    ):
        rows = results[kind]
        if not rows:
            print(f"{label:22s} (not available)")
            continue
        cpu = f"{agg(rows, 'cpu_per_s') * 100:.1f} % of a CPU" if "cpu_per_s" in rows[0] else ""
        missed = f"{sum(r['missed'] for r in rows)}" if "missed" in rows[0] else ""
        print(
            f"{label:22s} {agg(rows, 'p50') / 1000:9.1f}us {agg(rows, 'p99') / 1000:7.1f}us "
            f"{max(r['max'] for r in rows) / 1000:7.1f}us {missed:>7s} {cpu:>14s}"
        )
    for row in results["clients"]:
        per = row["delivered"] or []
        if per:
            print(
                f"telemetry messages per client per s (Settings.telemetry_per_message samples each): "
                f"min {min(per) / row['seconds']:.1f}, max {max(per) / row['seconds']:.1f}"
            )
    if results["cyclictest"] and results["alone"] and results["clients"]:
        ct = agg(results["cyclictest"], "p99")
        print(
            f"p99 ratio vs cyclictest: alone {agg(results['alone'], 'p99') / ct:.2f}, "
            f"with clients {agg(results['clients'], 'p99') / ct:.2f}"
        )


if __name__ == "__main__":
    main()
