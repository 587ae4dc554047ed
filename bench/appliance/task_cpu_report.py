"""Print where the appliance's event loop spent its CPU in a window of footprint.py --task-cpu's
snapshots (bench/appliance/task_cpu/sitecustomize.py): per task, per timed call, in microseconds
of CPU a second.

    .venv/bin/python bench/appliance/task_cpu_report.py /tmp/tc.<pid> [--last 11]
"""

from __future__ import annotations

import argparse
import json


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("file")
    ap.add_argument("--last", type=int, default=11, help="snapshots (5 s apart) the window spans")
    a = ap.parse_args()
    with open(a.file) as f:
        snaps = [json.loads(line) for line in f if line.strip()]
    if len(snaps) < 2:
        raise SystemExit(f"{a.file}: fewer than two snapshots")
    first, last = snaps[-min(a.last, len(snaps))], snaps[-1]
    t = last["t"] - first["t"]
    tasks = {k: v - first["tasks"].get(k, 0) for k, v in last["tasks"].items()}
    print(
        f"window {t:.0f} s: event loop thread {(last['main_ns'] - first['main_ns']) / 1e3 / t:.0f} us/s CPU, "
        f"{sum(tasks.values()) / 1e3 / t:.0f} us/s of it in task steps"
    )
    for name, ns in sorted(tasks.items(), key=lambda kv: -kv[1]):
        steps = last["steps"][name] - first["steps"].get(name, 0)
        if ns > 0:
            print(
                f"  {ns / 1e3 / t:8.1f} us/s  {steps / t:6.2f} steps/s  {ns / 1e3 / max(steps, 1):7.1f} us/step  {name}"
            )
    print("timed calls (any thread):")
    calls = {k: v - first["calls_ns"].get(k, 0) for k, v in last["calls_ns"].items()}
    for name, ns in sorted(calls.items(), key=lambda kv: -kv[1]):
        n = last["calls"][name] - first["calls"].get(name, 0)
        if ns > 0:
            print(f"  {ns / 1e3 / t:8.1f} us/s  {n / t:6.2f} calls/s  {ns / 1e3 / max(n, 1):7.1f} us/call  {name}")


if __name__ == "__main__":
    main()
