#!/usr/bin/env python3
"""Live tuning latency: Apply -> the loop's confirmation, with the 20-sim template at 1 kHz on the
simulated bench, sets of 6 parameters (its two PIDs' gains, values alternating so each is a
change). Two figures per set: the HTTP round trip of POST /api/params (what a browser's Apply
waits for: checks, the set written, the loop's answer, the change logged and published) and the
appliance's own part from writing the set to reading the loop's answer (`confirm_ms` of the
answer: at most a cycle plus the polling step). Prints p50/p99; not a timed test.
"""

from __future__ import annotations

import argparse
import time

from _common import appliance, summary_ms

NAMES = ["PID1\\Kp", "PID1\\Ki", "PID1\\Kd", "PID2\\Kp", "PID2\\Ki", "PID2\\Kd"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=300, help="sets (default 300)")
    args = ap.parse_args()
    with appliance() as server:
        run = server.start_run("template-20sim")
        with server.ws() as ws:
            ws.send({"type": "subscribe", "topics": ["state"]})
            ws.wait_type("ack")
            ws.command("initialise")
            ws.wait_state("INITIALISED", 10)
            ws.command("start")
            ws.wait_state("RUN", 10)
            http_ns: list[int] = []
            confirm_ns: list[int] = []
            for i in range(args.n):
                values = {n: 0.5 if i % 2 else 0.6 for n in NAMES}  # inside every proposed range
                t0 = time.monotonic_ns()
                r = server.http.post("/api/params", json={"values": values})
                http_ns.append(time.monotonic_ns() - t0)
                r.raise_for_status()
                confirm_ns.append(int(r.json()["confirm_ms"] * 1e6))
        freq = run["cycle_freq"]
        server.stop_run()
    print(f"parameter set latency, 6 parameters per set, loop at {freq} Hz (1 cycle = {1000 / freq:.1f} ms)")
    print(f"  POST /api/params round trip  {summary_ms(http_ns)}")
    print(f"  set written -> loop's answer {summary_ms(confirm_ns)}")


if __name__ == "__main__":
    main()
