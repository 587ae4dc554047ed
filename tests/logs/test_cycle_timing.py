"""Per-cycle framework timing (issue 4 item 2, XRF_LOG_TIMING=1): every cycle's wake-up jitter,
stage durations and missed periods as a log file of its own (cycle_timing.xrf), written by the loop's
helper thread (standalone) or by the appliance (its runs). Checked exactly against the status
histograms the loop keeps for the same cycles: same counts, sums and maxima."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from xrf_testing.harness import Server
from xrf_testing.logs_support import PROBE, REPO
from xrf_testing.loops import LoopProcess
from xrflab.channels import STAGE_NAMES
from xrflab.logs import open_log

TIMING_VARS = ["wakeup_ns", "fpga_ns", "data_ns", "cmd_ns", "monitor_ns", "hook_ns", "logger_ns", "cycle_ns", "missed"]


def _hists(lp: LoopProcess) -> dict[str, tuple[int, int, int]]:
    """(count, sum_ns, max_ns) per stage, exact (Channels.histograms() gives the mean only). Plain
    ints: a field of the cffi status struct does not keep the struct alive."""
    st = lp.ch.status_copy()
    return {
        name: (int(st.hist[i].count), int(st.hist[i].sum_ns), int(st.hist[i].max_ns))
        for i, name in enumerate(STAGE_NAMES)
    }


def test_standalone_loop_logs_every_cycle_and_matches_its_histograms(
    probe: Path, shm_name: str, tmp_path: Path
) -> None:
    lp = LoopProcess(
        probe,
        shm_name,
        tmp_path,
        capture=False,
        XRF_LOG_DIR=str(tmp_path),
        XRF_LOG_TIMING="1",
        XRF_TRANSPORT="sim",
        XRF_MAX_CYCLES="3000",
    )
    try:
        lp.command("initialise", "INITIALISED")
        lp.command("start", "RUN")
        assert lp.proc.wait(30) == 0
        status = lp.ch.status()
        log = open_log(tmp_path / "cycle_timing.xrf")
        assert log.skipped == [] and log.lost == 0
        assert [v.name for v in log.variables] == TIMING_VARS
        assert [v.code for v in log.variables] == [6] * 8 + [3]  # XRF2 codes: long int, int (periods)
        rec = log.records
        n = int(status.cycles)
        assert len(rec) == n == 3000
        assert np.array_equal(rec["seq"], np.arange(n, dtype=np.uint64))
        assert np.array_equal(rec["cycle"], np.arange(n, dtype=np.uint64))
        assert np.all(np.diff(rec["t_ns"]) > 0)
        # the same cycles as the status histograms, to the nanosecond
        hists = _hists(lp)
        for var, stage in (
            ("cycle_ns", "cycle"),
            ("hook_ns", "hook"),
            ("data_ns", "data"),
            ("cmd_ns", "cmd"),
            ("logger_ns", "logger"),
            ("monitor_ns", "monitor"),
            ("fpga_ns", "fpga"),
        ):
            count, sum_ns, max_ns = hists[stage]
            ran = rec[var][rec[var] >= 0]
            assert len(ran) == count, var
            assert int(ran.sum()) == sum_ns and (count == 0 or int(ran.max()) == max_ns), var
        count, sum_ns, _ = hists["wakeup"]
        assert int(np.clip(rec["wakeup_ns"], 0, None).sum()) == sum_ns and count == n
        assert int(rec["missed"].sum()) == status.missed
        assert hists["hook"][0] == n  # the controller ran in every cycle
        # The stages are timed with the CPU's counter, the cycle with the loop's clock
        # (xrf/cycle_counter.h, its rate measured against the clock before the loop runs). The
        # six stages are consecutive spans inside the cycle, so a wrong rate shows: too high and
        # they outgrow the cycle, too low and they shrink away from it.
        stages = sum(rec[v].astype(np.int64) for v in TIMING_VARS[1:7])
        cycle = rec["cycle_ns"].astype(np.int64)
        assert np.all(stages <= cycle + cycle // 1000 + 100), np.max(stages - cycle)
        assert np.median(stages / cycle) > 0.8, np.median(stages / cycle)
    finally:
        lp.stop()


def test_without_the_option_nothing_is_logged(probe: Path, shm_name: str, tmp_path: Path) -> None:
    lp = LoopProcess(
        probe, shm_name, tmp_path, capture=False, XRF_LOG_DIR=str(tmp_path), XRF_TRANSPORT="sim", XRF_MAX_CYCLES="200"
    )
    try:
        assert lp.proc.wait(30) == 0
        assert int(lp.ch.shm.timing_meta.ready) == 0
        assert int(lp.ch.shm.timing_ring.head) == 0
        assert not (tmp_path / "cycle_timing.xrf").exists()
    finally:
        lp.stop()


def test_a_run_with_timing_lists_it_as_a_log_and_downloads_it(server: Server, tmp_path: Path) -> None:
    server.stop_run()
    r = server.http.post("/api/runs", json={"build": PROBE, "log_timing": True}, timeout=300)
    assert r.status_code == 201, r.text
    run_id = r.json()["id"]
    for cmd in ("initialise", "start"):
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
    deadline = time.monotonic() + 20
    while server.http.get(f"/api/logs/runs/{run_id}").json()["run"]["cycles"] < 1500:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    server.stop_run()
    info = server.http.get(f"/api/logs/runs/{run_id}").json()
    files = {f["name"]: f for f in info["files"]}
    assert "cycle_timing.xrf" in files, files.keys()
    timing = files["cycle_timing.xrf"]
    # every cycle of the run, none lost, the loop's own count
    assert timing["records"] == info["run"]["cycles"] and timing["lost"] == 0
    assert [v["name"] for v in timing["variables"]] == TIMING_VARS
    got = server.http.get(f"/api/logs/runs/{run_id}/files/cycle_timing.xrf", params={"fmt": "csv"})
    assert got.status_code == 200
    env = dict(os.environ, PYTHONPATH=str(REPO / "appliance"))
    want = tmp_path / "cli.csv"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "xrflab.cli",
            "decode",
            str(server.data_dir / "runs" / str(run_id) / "cycle_timing.xrf"),
            "--to",
            "csv",
            "-o",
            str(want),
        ],
        check=True,
        env=env,
        capture_output=True,
    )
    assert got.content == want.read_bytes()
    # a run without the option has no timing log
    server.stop_run()
    r = server.http.post("/api/runs", json={"build": PROBE}, timeout=300)
    plain = r.json()["id"]
    for cmd in ("initialise", "start"):
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
    server.wait_cycles(plain, 100)
    server.stop_run()
    names = [f["name"] for f in server.http.get(f"/api/logs/runs/{plain}").json()["files"]]
    assert names and "cycle_timing.xrf" not in names
