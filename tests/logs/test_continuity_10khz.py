"""Sequence numbers continuous for a run at 10 kHz with 32 logged doubles while every core is
loaded by stress-ng: zero records lost, through the appliance's host log writer.

In the suite it runs 15 s (the log ring holds ~1.6 s at this rate, so 15 s is nine ring-fulls under
load); the 60 s soak is `bench/logs/soak.sh` (the same test, XRF_CONTINUITY_SECONDS=60)."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

from xrf_testing.harness import stop_server
from xrf_testing.logs_support import COST, start
from xrflab.logs import open_log

SECONDS = float(os.environ.get("XRF_CONTINUITY_SECONDS", "15"))


def test_10khz_32_doubles_under_load_loses_nothing(tmp_path: Path) -> None:
    # ./lab installs stress-ng; without the load this test would prove much less, so no skip.
    assert shutil.which("stress-ng"), "stress-ng is missing: apt-get install stress-ng (./lab does)"
    s = start(tmp_path / "data", loop_env={"XRF_FREQ": "10000", "XRF_BENCH_NVARS": "32"})
    stress = None
    try:
        run = s.start_run(COST)
        for cmd in ("initialise", "start"):
            assert s.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
        stress = subprocess.Popen(
            [
                "stress-ng",
                "--cpu",
                str(os.cpu_count() or 1),
                "--io",
                "1",
                "--vm",
                "1",
                "--vm-bytes",
                "128M",
                "--timeout",
                f"{int(SECONDS) + 5}s",
                "--quiet",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(SECONDS)  # the point: the soak's length, under load
        live = next(x for x in s.http.get("/api/logs/runs").json() if x["id"] == run["id"])
        assert live["live"] and live["log_lost"] == 0
        s.stop_run()
        r = next(x for x in s.http.get("/api/logs/runs").json() if x["id"] == run["id"])
        assert r["status"] == "ended" and r["log_lost"] == 0 and r["log_note"] == ""
        log = open_log(next((s.data_dir / "runs" / str(run["id"])).rglob("cost_*.xrf")))
        rec = log.records
        assert len(log.variables) == 32 and log.segments[0].header["cycle_freq"] == 10000
        assert log.skipped == [] and log.lost == 0 and len(rec) == r["log_records"] >= SECONDS * 10000 * 0.95
        assert np.array_equal(rec["seq"], np.arange(len(rec), dtype=np.uint64))
        c = rec["cycle"].astype(np.float64)
        assert np.array_equal(rec["d31"], rec["d0"] + 31 / 64.0)
        # d0 is the cycle in which a hook last filled the record: the record of a cycle whose
        # state runs no hook (a transition such as stop -> quit) repeats the previous values.
        # Every record's values are whole and consistent; nearly all hold their own cycle.
        stale = np.flatnonzero(rec["d0"] != c)
        assert len(stale) <= 10, stale
        assert np.all(rec["d0"][stale] < c[stale])
        print(
            f"\n{len(rec)} records, {r['misses']} deadline misses, lost {r['log_lost']}, "
            f"{len(stale)} records repeating an earlier cycle's values, last state {r['state']}"
        )
    finally:
        if stress is not None:
            stress.terminate()
            stress.wait(10)
        stop_server(s)
