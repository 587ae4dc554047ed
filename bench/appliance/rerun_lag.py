#!/usr/bin/env python3
"""Live rerun lag: how far behind the loop a viewer of the live rerun stream is.

A real appliance on the simulated bench runs a loop at 1 kHz (the RELbot example unless --build);
headless viewers read the run's live stream as the web viewer does, by gRPC-web through the
appliance's route (login cookie, same Origin), each in a process of its own (one per browser).
Each data frame is decoded as far as its chunk's ``time`` index (tests/xrf_testing/rerun_stream.py:
protobuf by hand, LZ4 block, Arrow IPC): the newest sample it carries, in wall-clock ns (the
loop's sample time + the run's wall offset, logs/rerun_live.py). lag = the frame's arrival wall time -
that sample's wall time, over every frame that carries one.

Cases (each a fresh run): 1 viewer, N viewers (--viewers, default 5), 1 viewer with the other core
loaded (``stress-ng --cpu 1`` pinned to the CPU the loop is not on). In each, after the live
window a late viewer connects: its catch-up time is from connecting until the first frame within
--edge s of the loop (the proxy replays the run's buffer first). Not a timed test; prints figures.
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
    ap.add_argument("--cases", default="1,n,stress", help="which of 1, n, stress")
    args = ap.parse_args()

    other = next((c for c in range(os.cpu_count() or 1) if c != args.cpu), None)
    cases = []
    for name in args.cases.split(","):
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
    with appliance(loop_env=loop_env) as server:
        for label, n, stress_cpu in cases:
            res = run_case(server, args.build, n, args.seconds, args.edge, stress_cpu)
            results.append((label, res))
            print(f"{label}: done", file=sys.stderr)

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
