"""The host log writer (xrflab.logs.host_writer.HostLogWriter) against a real loop process run with
XRF_LOG_WRITER=host: continuous records, kill -9 loses nothing that reached the ring, a full
disk stops logging cleanly (whole records only) while the loop goes on."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from xrf_testing.harness import wait_for
from xrf_testing.loops import LoopProcess
from xrflab.logs import open_log
from xrflab.logs.host_writer import MAX_PERIOD_S, WAIT_MS, HostLogWriter, drain_period
from xrflab.logs.timing_series import TIMING_FILE, TimingSeries


@pytest.fixture
def loop(probe: Path, shm_name: str):
    started: list[LoopProcess] = []

    def start(log_dir: Path, **env: str) -> LoopProcess:
        lp = LoopProcess(
            probe,
            shm_name,
            log_dir,
            capture=False,
            XRF_LOG_DIR=str(log_dir),
            XRF_LOG_WRITER="host",
            XRF_TRANSPORT="sim",
            **env,
        )
        started.append(lp)
        return lp

    yield start
    for lp in started:
        if lp.proc.poll() is None:
            lp.proc.kill()
            lp.proc.wait(5)


def _probe_ok(rec: np.ndarray) -> None:
    c = rec["cycle_2"]
    assert np.array_equal(rec["count"], c.astype(np.int32))
    assert np.array_equal(rec["value"], c * 0.25)


def _run_then_kill(lp: LoopProcess, cycles: int) -> None:
    """Drive the loop to RUN, let it log `cycles` more cycles, then kill -9 it mid-run."""
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    lp.wait_cycles(cycles)
    os.kill(lp.proc.pid, signal.SIGKILL)
    lp.proc.wait(5)


def _log_chunk_spans(proxy: Any, timeout: float, quiet: float) -> list[tuple[int, int]]:
    """(oldest, newest) `time` of each log chunk the run's proxy hands a reader now, in order."""
    import httpx

    from xrf_testing.grpcweb import READ_MESSAGES, read_messages
    from xrf_testing.rerun_stream import STORE_RECORDING, chunk_of

    spans: list[tuple[int, int]] = []

    def on_message(payload: bytes) -> None:
        chunk = chunk_of(payload)
        if chunk and chunk.store_kind == STORE_RECORDING and chunk.entity.startswith("/log/") and chunk.newest_time_ns:
            assert chunk.oldest_time_ns is not None
            spans.append((chunk.oldest_time_ns, chunk.newest_time_ns))

    with httpx.Client(base_url=proxy.read_url) as client:
        read_messages(client, READ_MESSAGES, timeout=timeout, quiet=quiet, on_message=on_message)
    return spans


def test_kill_9_loses_nothing_that_reached_the_ring(loop, tmp_path: Path) -> None:
    lp = loop(tmp_path)
    w = HostLogWriter(lp.ch, {"run": "7"}, tmp_path)
    w.start()
    _run_then_kill(lp, 500)
    stats = w.finish()
    status = lp.ch.status()
    assert stats.failed == "" and stats.lost == 0 and stats.unwritten == 0
    # every record the loop put into the ring is in the file: the appliance drained the rest
    assert stats.records == status.log_written
    log = open_log(Path(stats.files[0]))
    assert log.skipped == [] and log.lost == 0 and len(log) == stats.records
    assert np.array_equal(log.records["seq"], np.arange(len(log), dtype=np.uint64))
    assert log.segments[0].header["run"] == "7"
    _probe_ok(log.records)


def _freeze(lp: LoopProcess) -> None:
    """SIGSTOP the loop outside a status write (its block then reads whole); SIGCONT to go on."""
    for _ in range(100):
        os.kill(lp.proc.pid, signal.SIGSTOP)
        wait_for(lambda: Path(f"/proc/{lp.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "T", 5)
        if lp.ch.fresh_status() is not None:
            return
        os.kill(lp.proc.pid, signal.SIGCONT)
        time.sleep(0.01)
    raise AssertionError("the loop was always stopped mid status write")


def test_a_timing_line_is_one_status_copy_and_says_what_the_histograms_say(loop, tmp_path: Path) -> None:
    # The run's timing series (a line a second, by the host writer's thread) takes the counters
    # and every stage's figures from one copy of the 33 KB status block (it made two: the
    # histograms' and the counters'), and its file is opened once (issue 30 item 4).
    import json

    lp = loop(tmp_path)
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    lp.wait_cycles(300)
    _freeze(lp)  # the histograms hold still: the lines and the check see the same
    series = TimingSeries(lp.ch, tmp_path)
    copies = lp.ch.status_copies
    series.sample(force=True)
    assert lp.ch.status_copies - copies == 1
    series.sample(force=True)
    inode = (tmp_path / TIMING_FILE).stat().st_ino
    (tmp_path / TIMING_FILE).rename(tmp_path / "moved.jsonl")  # the same file, written on: kept open
    series.sample(force=True)
    series.close()
    assert not (tmp_path / TIMING_FILE).exists() and (tmp_path / "moved.jsonl").stat().st_ino == inode
    lines = [json.loads(x) for x in (tmp_path / "moved.jsonl").read_text().splitlines()]
    assert len(lines) == 3
    status, hists = lp.ch.status(), lp.ch.histograms()
    first, last = lines[0], lines[-1]
    assert first["cycles"] == last["cycles"] == status.cycles and last["log_written"] == status.log_written
    for name, h in hists.items():
        st = first["stages"][name]
        if not h.count:
            assert st == {"n": 0, "mean_ns": None, "p50_ns": None, "p99_ns": None, "max_ns": None}
            continue
        assert (st["n"], st["p50_ns"], st["p99_ns"], st["max_ns"]) == (
            h.count,
            h.percentile(50),
            h.percentile(99),
            h.max,
        )
        assert abs(st["mean_ns"] - h.mean) <= 0.05 + 1e-6  # to a tenth of a ns
        assert last["stages"][name]["n"] == 0  # nothing new since
    os.kill(lp.proc.pid, signal.SIGCONT)


def test_the_drain_period_follows_the_ring_capacity() -> None:
    # A quarter of the time a ring takes to fill at one record a cycle, within [WAIT_MS, MAX_PERIOD_S].
    assert drain_period(65536, 1000) == MAX_PERIOD_S  # RELbot: 65 536 slots of 88 bytes, 65 s
    assert drain_period(16384, 10000) == pytest.approx(16384 / 10000 / 4)  # 10 kHz, 32 doubles: 1.6 s
    assert drain_period(100, 10000) == WAIT_MS / 1000  # a tiny ring: as often as before
    assert drain_period(0, 1000) == WAIT_MS / 1000  # no layout yet


def test_records_are_drained_in_batches_and_none_is_lost(loop, tmp_path: Path) -> None:
    """Issue 30 item 4: the writer wakes a drain period apart, not on every doorbell (the loop
    rings it for telemetry many times a second), and every record still reaches the file."""
    lp = loop(tmp_path)
    w = HostLogWriter(lp.ch, {"run": "8"}, tmp_path, timing=False)
    w.start()
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    t0 = time.monotonic()
    lp.wait_cycles(3000)
    period = w.period()
    elapsed = time.monotonic() - t0
    os.kill(lp.proc.pid, signal.SIGKILL)  # the counts then stand still (the mapping is ours)
    lp.proc.wait(5)
    stats = w.finish()
    status = lp.ch.status()
    assert period == drain_period(w._chan.slots(), int(lp.ch.info["cycle_freq"])) and period >= 0.5
    # drains that found records: one per period, the final one, and one at RUN's first records
    assert w.drains <= elapsed / period + 3, (w.drains, elapsed, period)
    assert stats.failed == "" and stats.lost == 0 and stats.unwritten == 0
    assert stats.records == status.log_written >= 3000
    log = open_log(Path(stats.files[0]))
    assert log.skipped == [] and log.lost == 0 and len(log) == stats.records
    assert np.array_equal(log.records["seq"], np.arange(len(log), dtype=np.uint64))
    _probe_ok(log.records)


def test_the_timing_line_each_second_and_a_drain_every_few(loop, tmp_path: Path) -> None:
    """Issue 30 item 4, session 13: the writer's thread wakes once a second for the timing
    series' line, and drains the ring every MAX_PERIOD_S (4 s) of those, not at each (the drain
    was every second); every record is in the file after the run's end (finish drains the rest)."""
    lp = loop(tmp_path)
    w = HostLogWriter(lp.ch, {"run": "9"}, tmp_path)
    w.start()
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    t0 = time.monotonic()
    lp.wait_cycles(int(lp.ch.info["cycle_freq"]) * 9, timeout=60)
    period = w.period()
    drains = w.drains
    elapsed = time.monotonic() - t0
    os.kill(lp.proc.pid, signal.SIGKILL)
    lp.proc.wait(5)
    stats = w.finish()
    status = lp.ch.status()
    assert period == MAX_PERIOD_S == 4.0, period
    lines = (tmp_path / "timing.jsonl").read_text().splitlines()
    # a line a second (the run's record), drains a period apart (+ RUN's first records)
    assert len(lines) >= elapsed - 2, (len(lines), elapsed)
    assert drains <= elapsed / period + 2, (drains, elapsed)
    assert stats.failed == "" and stats.lost == 0 and stats.unwritten == 0
    assert stats.records == status.log_written >= 9 * int(lp.ch.info["cycle_freq"]) // 2
    log = open_log(Path(stats.files[0]))
    assert log.lost == 0 and len(log) == stats.records
    assert np.array_equal(log.records["seq"], np.arange(len(log), dtype=np.uint64))


def test_timing_taken_by_the_caller_is_written_at_the_drains(loop, tmp_path: Path) -> None:
    """Session 13: in the appliance the timing task takes the timing series' samples once a second
    (take_timing: one status copy each) and the writer's thread writes their lines at its drains,
    so it wakes for those only (every MAX_PERIOD_S), not once a second; by the run's end every
    sample taken has its line, in order, the last the final one."""
    lp = loop(tmp_path)
    w = HostLogWriter(lp.ch, {"run": "10"}, tmp_path, timing_in_thread=False)
    w.start()
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    t0 = time.monotonic()
    wakeups, copies = w.wakeups, lp.ch.status_copies
    for _ in range(9):
        time.sleep(1.0)  # the caller's second (the timing task's): time passing is the point
        w.take_timing()
    taken_copies = lp.ch.status_copies - copies
    woke = w.wakeups - wakeups
    elapsed = time.monotonic() - t0
    os.kill(lp.proc.pid, signal.SIGKILL)
    lp.proc.wait(5)
    stats = w.finish()
    assert taken_copies == 9, taken_copies  # one copy a sample, none by the thread
    assert woke <= elapsed / MAX_PERIOD_S + 2, (woke, elapsed)  # in its own time: ~9 or more
    lines = [json.loads(x) for x in (tmp_path / "timing.jsonl").read_text().splitlines()]
    assert len(lines) == 9 + 1, len(lines)  # and the run's end
    cycles = [x["cycles"] for x in lines]
    assert cycles == sorted(cycles) and cycles[-1] == lp.ch.status().cycles
    assert stats.failed == "" and stats.lost == 0


def test_disk_full_stops_logging_cleanly_and_the_loop_goes_on(loop, tmp_path: Path) -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root to mount a tiny tmpfs")
    disk = tmp_path / "disk"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)], check=True)
    try:
        lp = loop(disk)
        alarms: list[str] = []
        w = HostLogWriter(lp.ch, {}, disk, on_alarm=alarms.append, timing=False)
        w.start()
        lp.command("initialise", "INITIALISED")
        lp.command("start", "RUN")
        # 48-byte stride at 1 kHz: 256 KiB fill in ~5 s
        wait_for(lambda: w.stats.failed, 20, "the disk to fill")
        c = lp.ch.status().cycles
        lp.wait_cycles(300)  # the loop goes on
        assert lp.ch.status().state_name == "RUN" and lp.ch.status().cycles >= c + 300
        lp.ch.send_command("stop")
        lp.wait_state("STOPPED")  # quit is accepted in STOPPED, not while STOPPING
        lp.ch.send_command("quit")
        assert lp.proc.wait(10) == 0
        stats = w.finish()
        assert len(alarms) == 1 and "No space left" in alarms[0] and "logging stopped" in alarms[0]
        assert stats.unwritten > 0
        log = open_log(Path(stats.files[0]))
        # nothing written is damaged: whole records only, continuous, correct values
        assert log.skipped == [] and log.lost == 0 and len(log) == stats.records > 1000
        assert np.array_equal(log.records["seq"], np.arange(len(log), dtype=np.uint64))
        _probe_ok(log.records)
        # the counts add up: every record the loop logged is in the file or counted as unwritten
        assert stats.records + stats.unwritten + stats.lost == lp.ch.status().log_written + stats.lost
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def test_live_rerun_stream_takes_records_and_telemetry(loop, tmp_path: Path, caplog) -> None:
    """The live stream (decimated records + telemetry) reaches the run's own rerun proxy, which
    listens on 127.0.0.1 only; the next run's proxy replaces it; the blueprint has one view per
    variable group and the telemetry views."""
    import logging

    import httpx

    from xrf_testing.grpcweb import READ_MESSAGES, read_messages
    from xrflab.logs.rerun_live import LiveRerun
    from xrflab.logs.rerun_servers import LiveProxy

    caplog.set_level(logging.ERROR, logger="xrflab.logs.live")
    lp = loop(tmp_path)
    proxy = LiveProxy.open_for_run(42, "alice")
    try:
        assert proxy.local_url == f"rerun+http://127.0.0.1:{proxy.port}/proxy" and LiveProxy.current() is proxy
        assert proxy.ensure_running()  # a viewer reads it (the appliance's read route starts it and counts it)
        proxy.readers = 1
        stream = LiveRerun(proxy, lp.ch, run_id=42)
        # as logs/live.py wires it: drained every 20 ms while a viewer watches
        w = HostLogWriter(lp.ch, {}, tmp_path, on_records=stream.feed, timing=False, fast=stream.watched)
        w.start()
        _run_then_kill(lp, 1000)
        w.finish()
        stream.close()
        stream._thread.join(10)
        assert stream._names == ["cycle_2", "flag", "letter", "count", "ratio", "value"]
        assert stream.dropped == 0
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
        # (and the blueprint, which rerun never drops from the window: the group's view, the telemetry's)
        keys = (
            b"run-42",
            b"cycle_2",
            b"ratio",
            b"telemetry/enc",
            b"log: signals",
            b"/telemetry/xeno2ros",
            b"TimeSeries",
        )
        with httpx.Client(base_url=proxy.read_url) as client:
            got = read_messages(client, READ_MESSAGES, until=lambda d: all(k in d for k in keys))
        for key in keys:
            assert key in got.data, key
        # the next run gets a new proxy; the old one is stopped
        nxt = LiveProxy.open_for_run(43, "bob")
        assert proxy.proc.poll() is not None and LiveProxy.current() is nxt and nxt.port != 0
    finally:
        LiveProxy.stop_all()
    assert LiveProxy.current() is None


def test_a_live_batch_takes_every_record_queued_by_then(loop, tmp_path: Path) -> None:
    """The live recording's thread sends, in a round, every record queued by then (issue 31 bug 6,
    session 11). It took one drain of the writer per turn: a round that took long (its connection
    at the first viewer, rerun's import with it: 1-2 s under load) left the drains of that time
    queued, and the batch it sent held only the oldest of them (1.4 s old at the first viewer,
    measured), the rest half a second later. Here many drains are queued at once (as behind a
    slow round), and the first log chunk that reaches the proxy ends with the newest of them."""

    from xrflab.logs.rerun_live import SEND_PERIOD_S, LiveRerun
    from xrflab.logs.rerun_servers import LiveProxy

    lp = loop(tmp_path)
    proxy = LiveProxy.open_for_run(45, "alice")
    try:
        assert proxy.ensure_running()
        proxy.readers = 1  # watched: the recording connects and sends
        stream = LiveRerun(proxy, lp.ch, run_id=45)
        wait_for(lambda: stream.rec is not None, 30, "the recording connected")
        wait_for(lambda: stream._q.empty(), 10, "the sending thread waiting")
        time.sleep(2 * SEND_PERIOD_S)  # on purpose: its last round long enough ago that the next sends at once
        dtype = np.dtype([("seq", "<u8"), ("cycle", "<u8"), ("t_ns", "<i8"), ("value", "<f8")])
        n, drains = stream._bucket, 40  # whole min/max buckets: none is held back for the next batch
        t0 = time.monotonic_ns()
        batches = []
        for k in range(drains):  # the writer's drains, queued faster than the thread takes them
            cycles = np.arange(k * n, (k + 1) * n, dtype=np.uint64)
            rec = np.zeros(n, dtype=dtype)
            rec["seq"], rec["cycle"], rec["t_ns"], rec["value"] = (
                cycles,
                cycles,
                t0 + cycles.astype(np.int64) * 1000,
                1.0,
            )
            batches.append(rec)
        for rec in batches:
            stream.feed(rec)
        newest = int(batches[-1]["t_ns"][-1]) + stream._wall_offset
        # (a few rounds: a batch sent with what the first left behind would come SEND_PERIOD_S later)
        log_chunks = [newest_ns for _, newest_ns in _log_chunk_spans(proxy, 6 * SEND_PERIOD_S, 4 * SEND_PERIOD_S)]
        stream.close()
        stream._thread.join(10)
        assert log_chunks, "no log chunk reached the proxy"
        assert log_chunks == [newest], (
            f"{len(log_chunks)} batches of the records queued at once, the first ending "
            f"{(newest - min(log_chunks)) / 1e6:.0f} ms of the loop's time before the newest: not every drain "
            "queued by then went with the first"
        )
    finally:
        LiveProxy.stop_all()


def test_a_viewers_first_batch_is_the_live_edge_of_what_its_arrival_drained(loop, tmp_path: Path) -> None:
    """A viewer's arrival wakes the host writer, whose drain hands over all it read since its last
    drain: up to host_writer.MAX_PERIOD_S (4 s) of records while nobody watched. The viewer's
    first batch is the last SEND_PERIOD_S of them (the live edge), not all 4 s (CI, session 13:
    the viewer's first frame began 3.1 s before it was opened). Here 4 s of the loop's records
    arrive at once at the first viewer; what reaches the proxy starts SEND_PERIOD_S before the
    newest and ends with it."""

    from xrflab.logs.rerun_live import SEND_PERIOD_S, LiveRerun
    from xrflab.logs.rerun_servers import LiveProxy

    lp = loop(tmp_path)
    proxy = LiveProxy.open_for_run(47, "alice")
    try:
        assert proxy.ensure_running()
        proxy.readers = 1  # a viewer: the recording connects
        stream = LiveRerun(proxy, lp.ch, run_id=47)
        wait_for(lambda: stream.rec is not None, 30, "the recording connected")
        freq = stream._freq
        period_ns = 1_000_000_000 // freq
        dtype = np.dtype([("seq", "<u8"), ("cycle", "<u8"), ("t_ns", "<i8"), ("value", "<f8")])
        cycles = np.arange(0, MAX_PERIOD_S * freq, dtype=np.uint64)  # one drain of a writer nobody watched
        rec = np.zeros(len(cycles), dtype=dtype)
        t0 = time.monotonic_ns()
        rec["seq"], rec["cycle"], rec["t_ns"], rec["value"] = (
            cycles,
            cycles,
            t0 + cycles.astype(np.int64) * period_ns,
            1.0,
        )
        for part in np.array_split(rec, 40):  # as a drain hands it over: in pieces, at once
            stream.feed(part)
        newest = int(rec["t_ns"][-1]) + stream._wall_offset
        spans = _log_chunk_spans(proxy, 6 * SEND_PERIOD_S, 4 * SEND_PERIOD_S)
        stream.close()
        stream._thread.join(10)
        assert spans, "no log chunk reached the proxy"
        oldest = min(o for o, _ in spans)
        assert max(n for _, n in spans) == newest, "the newest record was not sent"
        assert newest - oldest < SEND_PERIOD_S * 1e9, (
            f"the viewer's first records began {(newest - oldest) / 1e9:.2f} s before the newest: "
            f"more than the live edge ({SEND_PERIOD_S} s)"
        )
    finally:
        LiveProxy.stop_all()


def test_a_reader_joining_with_no_page_served_wakes_the_live_recording(loop, tmp_path: Path) -> None:
    """The live recording's thread sleeps while nobody watches (no look on a timer: issue 30
    item 4). A reader that joins with no viewer's page served just before (``expect_viewer``:
    a page older than its window, a reader of its own) wakes it, and a loop that logs nothing
    yet (no records to wake it through the writer) still gets its telemetry sent."""
    from xrflab.logs.rerun_live import LiveRerun
    from xrflab.logs.rerun_servers import LiveProxy

    lp = loop(tmp_path)
    proxy = LiveProxy.open_for_run(48, "alice")
    stream = None
    try:
        assert proxy.ensure_running()
        stream = LiveRerun(proxy, lp.ch, run_id=48)
        lp.command("initialise", "INITIALISED")  # telemetry, no log records
        wait_for(lambda: stream._q.empty(), 10, "the sending thread asleep")
        assert stream.rec is None  # nobody watched: never connected
        proxy.reader_joined()
        wait_for(lambda: stream.rec is not None, 20, "the recording connected for the reader")
    finally:
        if stream is not None:
            stream.close()
            stream._thread.join(10)
        LiveProxy.stop_all()


def test_a_live_viewer_coming_wakes_the_writer(loop, tmp_path: Path, monkeypatch) -> None:
    """A live viewer's arrival (its page served: ``LiveProxy.expect_viewer``) makes the host writer
    drain at once, not at the end of its period (up to a second while nobody watches): the
    viewer's first records, and the read route's wait for the recording to resume, waited for it
    (issue 31 bug 6, session 11). The period is made long here, so the drain is the wake's."""
    from xrflab.logs import host_writer
    from xrflab.logs.rerun_live import LiveRerun
    from xrflab.logs.rerun_servers import LiveProxy

    monkeypatch.setattr(host_writer, "MAX_PERIOD_S", 600.0)
    lp = loop(tmp_path)
    proxy = LiveProxy.open_for_run(46, "alice")
    w = HostLogWriter(lp.ch, {}, tmp_path, timing=False)
    try:
        stream = LiveRerun(proxy, lp.ch, run_id=46, wake_writer=w.wake)
        w.set_on_records(stream.feed, fast=stream.watched)
        w.start()
        lp.command("initialise", "INITIALISED")
        lp.command("start", "RUN")
        lp.wait_cycles(200)
        assert w.period() > 30, w.period()  # the next periodic drain is far away
        before = w.drains
        proxy.expect_viewer()
        wait_for(lambda: w.drains > before, 20, "the writer's drain once a viewer is coming")
        wait_for(lambda: stream._names is not None, 20, "the viewer's first records sent")
    finally:
        w.finish()
        if "stream" in locals():
            stream.close()
            stream._thread.join(10)
        LiveProxy.stop_all()


def test_records_go_to_the_live_stream_only_while_someone_takes_them(loop, tmp_path: Path) -> None:
    # on_records (the live rerun stream) gets the drained records while fast() says a viewer takes
    # them, and nothing (no copy of them made) while nobody does; every record is in the file
    # either way (issue 30 item 4: the copy of every record, each drain, with no viewer open).
    lp = loop(tmp_path)
    viewer = threading.Event()
    taken: list[np.ndarray] = []
    w = HostLogWriter(lp.ch, {}, tmp_path, timing=False)
    w.set_on_records(taken.append, fast=viewer.is_set)
    w.start()
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    lp.wait_cycles(1500)
    w.drain()
    assert taken == []  # nobody watching: nothing handed over
    viewer.set()
    w.wake()
    start = lp.ch.status().log_written
    wait_for(lambda: sum(len(r) for r in taken) > 0 and taken[-1]["seq"][-1] >= start + 200, 10, "live records")
    viewer.clear()
    w.drain()  # after any drain under way (the lock): from here on fast() is false
    seen = sum(len(r) for r in taken)
    lp.wait_cycles(500)
    w.drain()
    assert sum(len(r) for r in taken) == seen  # the viewer left: nothing more handed over
    os.kill(lp.proc.pid, signal.SIGKILL)  # the counts then stand still (the mapping is ours)
    lp.proc.wait(5)
    stats = w.finish()
    seqs = np.concatenate([r["seq"] for r in taken])
    # While watched: every record, in order.
    assert np.array_equal(seqs, np.arange(seqs[0], seqs[0] + len(seqs), dtype=np.uint64))
    assert stats.records == lp.ch.status().log_written and stats.lost == 0  # the file has every record
    assert seqs[0] > 0  # the records drained before the viewer came were not handed over


def test_live_rerun_stream_sends_nothing_without_a_viewer(loop, tmp_path: Path) -> None:
    """With no viewer on the run's proxy the live stream neither connects nor sends (issue 30
    item 4: work and the rerun SDK's memory for nobody); the log file still gets every record."""
    import httpx

    from xrf_testing.grpcweb import READ_MESSAGES, read_messages
    from xrflab.logs.rerun_live import LiveRerun
    from xrflab.logs.rerun_servers import LiveProxy

    lp = loop(tmp_path)
    proxy = LiveProxy.open_for_run(44, "alice")
    try:
        assert proxy.readers == 0
        stream = LiveRerun(proxy, lp.ch, run_id=44)
        # Its sending thread sleeps until a viewer comes (LiveProxy.on_viewer), not looking for
        # one on a timer: counted as the thread's voluntary context switches (it woke twice a
        # second in session 9, 8-9 in 4 s; once a second in session 13, 4-5).
        status = Path(f"/proc/self/task/{stream._thread.native_id}/status")

        def woke() -> int:
            line = next(ln for ln in status.read_text().splitlines() if ln.startswith("voluntary_ctxt_switches:"))
            return int(line.split()[1])

        first = woke()
        time.sleep(4)  # the point: a window of no viewer whose wake-ups are counted
        got = woke() - first
        assert got <= 1, f"the sending thread woke {got} times in 4 s with no viewer"
        w = HostLogWriter(lp.ch, {}, tmp_path, on_records=stream.feed, timing=False)
        w.start()
        _run_then_kill(lp, 1000)
        stats = w.finish()
        stream.close()
        stream._thread.join(10)
        assert stats.records >= 1000, stats
        assert stream.rec is None and stream._names is None and stream.dropped == 0
        # a reader straight on the proxy (not counted: not through the appliance) finds no recording
        assert not proxy.running()  # nobody watched: its process never started
        assert proxy.ensure_running()
        with httpx.Client(base_url=proxy.read_url) as client:
            got = read_messages(client, READ_MESSAGES, until=lambda d: b"run-44" in d, timeout=3, quiet=2)
        assert b"run-44" not in got.data
    finally:
        LiveProxy.stop_all()


def _whole_header(path: Path) -> bytes | None:
    """The first segment header of `path` once all of it is in the file."""
    import struct

    from xrflab.logs.logformat import ALIGN, JSON_LEN_OFFSET, PREFIX_SIZE

    raw = path.read_bytes() if path.exists() else b""
    if len(raw) < PREFIX_SIZE:
        return None
    end = (PREFIX_SIZE + struct.unpack_from("<I", raw, JSON_LEN_OFFSET)[0] + ALIGN - 1) // ALIGN * ALIGN
    return raw[:end] if len(raw) >= end else None


def test_host_and_loop_write_the_same_header_bytes(probe: Path, shm_name: str, tmp_path: Path) -> None:
    """A segment header has one composer (logformat.h): the loop's own writer and the host writer,
    given the same log layout, identity and start time, produce the same bytes; for the logger's
    file and the per-cycle timing file, with identity texts that need escaping."""
    import json

    from xrflab.logs.logformat import PREFIX_SIZE

    identity = {"project": 'pro"ject \u00fc', "build": "b\\1\ttab", "run": "77"}
    lp = LoopProcess(
        probe,
        shm_name,
        tmp_path,
        capture=False,
        XRF_LOG_DIR=str(tmp_path),
        XRF_LOG_WRITER="process",
        XRF_TRANSPORT="sim",
        XRF_LOG_TIMING="1",
        XRF_PROJECT=identity["project"],
        XRF_BUILD_ID=identity["build"],
        XRF_RUN_ID=identity["run"],
    )
    try:
        lp.command("initialise", "INITIALISED")
        written: dict[str, bytes | None] = {}
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            logs = sorted((tmp_path / "logs").glob("probe_*.xrf"))
            written = {
                "log": _whole_header(logs[0]) if logs else None,
                "cycle_timing": _whole_header(tmp_path / "cycle_timing.xrf"),
            }
            if all(written.values()):
                break
            time.sleep(0.05)
        for source, raw in written.items():
            assert raw is not None, f"the loop wrote no {source} file"
            header = json.loads(raw[PREFIX_SIZE:].rstrip(b"\0"))
            assert {k: header[k] for k in identity} == identity and header["pid"] == lp.proc.pid
            w = HostLogWriter(lp.ch, identity, tmp_path, timing=False, source=source)
            assert w.segment_header(header["start_unix_ns"], header["start_mono_ns"]) == raw, source
    finally:
        lp.stop()
