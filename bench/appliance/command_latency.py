#!/usr/bin/env python3
"""Command latency browser -> loop -> browser: from a WebSocket client sending a command to the
`state` message showing the new state arriving at that same client, with the RELbot example at
1 kHz on the simulated bench. Commands alternate pause (RUN -> PAUSING -> PAUSED) and start
(PAUSED -> RUN); the time counted ends at the first state message with the target state.

Target (issue 3): p50 <= 1 cycle + 2 ms = 3 ms. Prints p50/p99; not a timed test.
"""

from __future__ import annotations

import argparse
import json
import time

from _common import appliance, pct, summary_ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=200, help="commands of each kind (default 200)")
    args = ap.parse_args()

    with appliance() as server:
        run = server.start_run("relbot")
        with server.ws() as ws:
            ws.send({"type": "subscribe", "topics": ["state"]})  # only what we measure
            ws.wait_type("ack")
            ws.command("initialise")
            ws.wait_state("INITIALISED")
            ws.command("start")
            ws.wait_state("RUN")
            lat: dict[str, list[int]] = {"pause": [], "start": []}
            for i in range(args.n * 2):
                cmd, target = ("pause", "PAUSED") if i % 2 == 0 else ("start", "RUN")
                t0 = time.monotonic_ns()
                ws.conn.send(json.dumps({"type": "command", "cmd": cmd}))
                while True:
                    m = json.loads(ws.conn.recv(timeout=5))
                    if m.get("type") == "state" and m.get("name") == target:
                        lat[cmd].append(time.monotonic_ns() - t0)
                        break
                # Drain the ack so it does not count toward the next command.
                while True:
                    m = json.loads(ws.conn.recv(timeout=5))
                    if m.get("type") == "ack":
                        break
        freq = run["cycle_freq"]
    print(f"command latency, WebSocket send -> state observed, loop at {freq} Hz (1 cycle = {1000 / freq:.1f} ms)")
    for cmd, values in lat.items():
        print(f"  {cmd:6s} {summary_ms(values)}")
    both = lat["pause"] + lat["start"]
    p50 = pct([v / 1e6 for v in both], 50)
    target = 1000 / freq + 2
    print(f"  all    {summary_ms(both)}")
    print(f"  target p50 <= {target:.1f} ms: {'met' if p50 <= target else 'NOT met'} ({p50:.3f} ms)")


if __name__ == "__main__":
    main()
