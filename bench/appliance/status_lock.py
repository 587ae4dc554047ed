#!/usr/bin/env python3
"""How long one read of a loop's status block can hold its caller (the appliance's event loop)
when the block is locked (channels/status.py): the first read of a run of locked reads (its short
spin), and the reads after it (one try each). A segment made as a loop's (tests/xrf_testing
testloop.create_for_test), its seq set odd by hand: what a loop preempted mid-write or a hostile
one leaves. Before, every such read spun 20 ms. Prints median, p99 and max; not a timed test.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

from xrf_testing.testloop import create_for_test  # noqa: E402
from xrflab import channels  # noqa: E402


def ms(xs: list[float], p: float) -> str:
    xs = sorted(xs)
    return f"{xs[min(len(xs) - 1, int(len(xs) * p))] * 1e3:.3f} ms"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=300, help="runs of locked reads")
    ap.add_argument("--then", type=int, default=20, help="reads after the first in each run")
    args = ap.parse_args()
    name = f"xrf-bench-status-{os.getpid()}"
    ch = create_for_test(name)
    first: list[float] = []
    later: list[float] = []
    try:
        for _ in range(args.n):
            ch.status()  # a good copy: the block even
            ch.shm.status.seq += 1  # locked
            t0 = time.perf_counter()
            ch.status()
            first.append(time.perf_counter() - t0)
            for _ in range(args.then):
                t0 = time.perf_counter()
                ch.status()
                later.append(time.perf_counter() - t0)
            ch.shm.status.seq += 1  # the write finished: the next round starts a new run
    finally:
        ch.close()
        channels.shm_path(name).unlink(missing_ok=True)
    print(
        f"first locked read: median {statistics.median(first) * 1e3:.3f} ms, p99 {ms(first, 0.99)}, max {ms(first, 1)}"
    )
    print(
        f"later locked reads: median {statistics.median(later) * 1e3:.3f} ms, p99 {ms(later, 0.99)}, max {ms(later, 1)}"
    )
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
