"""The loop process end to end: a real controller executable, its shared memory, real signals."""

from __future__ import annotations

import json
import signal
import statistics
import struct
import time

import numpy as np

from xrflab.channels import lib
from xrflab.logs import open_log
from xrflab.logs.logformat import MAGIC


def test_state_visible_from_first_cycle_and_no_motion_before_initialise(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    lp.wait_cycles(20)
    st = lp.ch.status()
    assert st.state_name == "IDLE" and st.running
    # The probe asks for PWM 300 from its constructor on; nothing moves before initialise.
    assert list(lp.ch.shm.sim.pwm) == [0] * lib.XRF_MAX_CHANNELS
    # Xeno2Ros is published from the first cycle, without any Ros2Xeno having arrived.
    reader = lp.ch.telemetry_reader(from_start=True)
    first = reader.read()
    assert first and first[0].cycle <= 1 and first[0].state == 1
    assert all(t.pwm == [0, 0, 0, 0] for t in first)

    assert lp.command("initialise").accepted
    lp.wait_state("INITIALISED")
    lp.wait_cycles(5)
    assert lp.ch.shm.sim.pwm[0] == 300


def test_rejected_commands_carry_a_reason_and_leave_the_loop_running(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    res = lp.command("start")
    assert not res.accepted and res.state == 1
    assert "start is not allowed in state IDLE" in res.reason and "initialise" in res.reason
    res = lp.command(42)
    assert not res.accepted and "42 is not a command" in res.reason
    st = lp.ch.status()
    assert st.last_rejected_cmd == 42 and st.rejected_count == 2
    lp.wait_cycles(10)
    assert lp.command("initialise").accepted


def test_pwm_limit_default_and_configured(run_loop, probe_exe):
    for env, expected in (({}, 409), ({"XRF_PWM_LIMIT": "0.5"}, 1023)):
        lp = run_loop(probe_exe, **env)
        lp.command("initialise")
        lp.wait_state("INITIALISED")
        assert lp.command("start").accepted
        lp.ch.write_ros2xeno({"pwm1": 2000})
        lp.wait_cycles(5)
        assert lp.ch.shm.sim.pwm[0] == expected
        lp.ch.write_ros2xeno({"pwm1": -2000})
        lp.wait_cycles(5)
        assert lp.ch.shm.sim.pwm[0] == -expected
        lp.stop()


def test_walk_through_the_states_and_quit(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    walk = [
        ("initialise", "INITIALISED"),
        ("start", "RUN"),
        ("pause", "PAUSED"),
        ("start", "RUN"),
        ("pause", "PAUSED"),
        ("reset", "INITIALISED"),
        ("start", "RUN"),
        ("stop", "STOPPED"),
    ]
    for cmd, state in walk:
        res = lp.command(cmd)
        assert res.accepted, f"{cmd}: {res.reason}"
        lp.wait_state(state)
    assert lp.command("quit").accepted
    code, out = lp.finish()
    assert code == 0
    assert "missed" in out and "cycles" in out
    assert lp.ch.status().state_name == "QUIT" and not lp.ch.status().running
    assert list(lp.ch.shm.sim.pwm) == [0] * lib.XRF_MAX_CHANNELS


def test_hook_error_goes_to_error_with_the_value(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    lp.command("initialise")
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.ch.write_ros2xeno({"run_return": -17})
    lp.wait_state("ERROR")
    st = lp.ch.status()
    assert st.last_error == -17
    lp.wait_cycles(5)
    assert lp.ch.shm.sim.pwm[0] == 0  # ERROR keeps the motors off


def test_overrun_counts_misses_and_the_grid_does_not_shift(run_loop, probe_exe):
    lp = run_loop(probe_exe, XRF_PRIO="50")
    lp.command("initialise")
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.wait_state("RUN")
    lp.wait_cycles(200)
    before = lp.ch.status()
    # 3.4 ms of work in a 1 ms period, for a while: every such cycle passes over the 3 periods
    # that begin while it works, and the next one starts at the 4th boundary.
    lp.ch.write_ros2xeno({"overrun_us": 3400})
    time.sleep(0.3)  # the point: overrunning for a while (~75 cycles at 4 ms)
    lp.ch.write_ros2xeno({"overrun_us": 0})
    during = lp.ch.status()
    assert during.missed - before.missed >= 3 * 20
    # Not a cycle per period: the periods it could not serve are missed, not run late.
    assert during.cycles - before.cycles < during.missed - before.missed
    reader = lp.ch.telemetry_reader()
    lp.wait_cycles(400)
    samples = reader.read()
    st = lp.ch.status()
    assert len(samples) > 300
    # Wake-up times stay on t0 + k*T: the phase against the grid is jitter, not the 0.4 ms of
    # fractional overrun the grid would have absorbed had it shifted.
    period = 1_000_000
    phases = [(t.t_ns - st.t_start_ns) % period for t in samples]
    phases = [p if p < period // 2 else p - period for p in phases]
    assert abs(statistics.median(phases)) < 150_000
    assert lp.ch.status().state_name == "RUN"


def test_one_overrun_skips_to_the_next_boundary_and_counts_the_periods_passed_over(run_loop, probe_exe, tmp_path):
    """Firm deadlines (docs/rt_core/runtime.md, "After an overrun"): a cycle that works for 3.5
    periods once has lost the periods that began meanwhile. The next cycle starts at the first
    boundary still ahead, after a sleep (no late cycles back to back), and the periods passed
    over are counted as missed: in the status, per cycle in the timing log and in the summary."""
    period = 1_000_000
    lp = run_loop(probe_exe, XRF_PRIO="50", XRF_LOG_TIMING="1", XRF_LOG_DIR=str(tmp_path / "data"))
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    lp.wait_cycles(100)
    lp.ch.write_ros2xeno({"spin_us": 3500, "spin_seq": 1})
    lp.wait_cycles(200)
    lp.proc.send_signal(signal.SIGINT)
    code, out = lp.finish()
    assert code == 0, out
    st = lp.ch.status()
    log = open_log(tmp_path / "data" / "cycle_timing.xrf")
    rec = log.records
    assert log.lost == 0 and len(rec) == st.cycles
    wake = rec["t_ns"].astype(np.int64)
    deadline = wake - rec["wakeup_ns"].astype(np.int64)
    end = wake + rec["cycle_ns"].astype(np.int64)
    missed = rec["missed"].astype(np.int64)
    # Every cycle starts on the grid, and at a boundary that was still ahead when the cycle
    # before it ended: no late period is run (catching up would start cycles whose boundary
    # had passed, one right after the other).
    assert np.all((deadline - st.t_start_ns) % period == 0)
    assert np.all(deadline[1:] > end[:-1]), np.flatnonzero(deadline[1:] <= end[:-1])
    # The next cycle's boundary is the first one after the end; the ones between are missed.
    assert np.all(deadline[1:] - period <= end[:-1])
    assert np.array_equal(np.diff(deadline), (missed[:-1] + 1) * period)
    spun = np.flatnonzero(rec["cycle_ns"] >= 3_500_000)
    assert len(spun) >= 1 and missed[spun[0]] >= 3, (spun, missed[spun])
    # Nothing hidden: the status, the timing log and XRF2's summary line agree.
    assert int(missed.sum()) == st.missed
    assert f"{st.cycles} cycles, {st.missed} missed" in out, out[-500:]
    assert (deadline[-1] - deadline[0]) // period + 1 == len(rec) + int(missed[:-1].sum())


def test_crash_leaves_the_last_state_in_shared_memory(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    lp.command("initialise")
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.wait_state("RUN")
    lp.ch.write_ros2xeno({"crash": True})
    code, _ = lp.finish()
    assert code == -signal.SIGSEGV
    st = lp.ch.status()
    assert st.state_name == "RUN" and st.running  # it died; it did not return
    assert st.cycles > 0


def test_sigint_is_a_safe_stop(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    lp.command("initialise")
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.wait_cycles(20)
    assert lp.ch.shm.sim.pwm[0] == 300
    lp.proc.send_signal(signal.SIGINT)
    code, out = lp.finish()
    assert code == 0 and "cycles" in out
    assert list(lp.ch.shm.sim.pwm) == [0] * lib.XRF_MAX_CHANNELS
    assert not lp.ch.status().running


def test_host_heartbeat_loss_stops_the_run(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    lp.command("initialise")
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.wait_state("RUN")
    lp.ch.configure_host_timeout(100, "stop")
    for _ in range(10):  # a live host: nothing happens
        lp.ch.host_heartbeat()
        time.sleep(0.03)
    assert lp.ch.status().state_name == "RUN"
    lp.wait_state("STOPPED", timeout=2)  # the host went quiet
    assert lp.ch.status().host_lost == 1


def test_the_watcher_beats_for_a_stalled_event_loop_within_its_grace(run_loop, probe_exe):
    """The safety watcher's thread beats the host heartbeat while the host's event loop was alive
    within the grace (watch.h host_beat_ns): a host that only stalls (here: never beats itself
    after one sign of life) keeps the run going past host_timeout_ms, and the run stops once
    the grace is over; a watcher that does not beat (host_beat 0) leaves it to the host."""
    from xrflab.server.runs.safety import SafetyWatcher

    lp = run_loop(probe_exe)
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    w = SafetyWatcher(
        lp.proc.pid, lp.ch, hang_timeout_ms=2000, check_ms=20, force_sim=True, host_beat_ms=50, host_grace_ms=1500
    )
    try:
        w.host_alive()
        lp.ch.configure_host_timeout(300, "stop")  # beats once itself, then only the watcher does
        time.sleep(1.0)  # time passing: more than three host timeouts without a beat from here
        assert lp.ch.status().state_name == "RUN" and lp.ch.status().host_lost == 0
        lp.wait_state("STOPPED", timeout=3)  # the grace is over: the watcher stops beating
        assert lp.ch.status().host_lost == 1
    finally:
        w.stop()


def test_a_watcher_without_host_beats_leaves_the_heartbeat_to_the_host(run_loop, probe_exe):
    from xrflab.server.runs.safety import SafetyWatcher

    lp = run_loop(probe_exe)
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    w = SafetyWatcher(lp.proc.pid, lp.ch, hang_timeout_ms=2000, check_ms=20, force_sim=True)
    try:
        w.host_alive()
        lp.ch.configure_host_timeout(300, "stop")
        lp.wait_state("STOPPED", timeout=2)
        assert lp.ch.status().host_lost == 1
    finally:
        w.stop()


def test_monitor_is_decimated_and_reaches_the_host(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    reader = lp.ch.monitor_reader()
    lp.command("initialise")
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.wait_cycles(500)
    lines = reader.read()
    # monitor_freq 10 Hz at 1 kHz: every 100th cycle prints.
    cycles = [ln.cycle for ln in lines]
    assert len(lines) >= 3
    assert all(b - a == 100 for a, b in zip(cycles, cycles[1:]))
    assert all(ln.text.startswith("probe cycle") for ln in lines)


def test_log_file_is_self_describing_with_continuous_sequence(run_loop, probe_exe, tmp_path):
    lp = run_loop(probe_exe, XRF_LOG_DIR=str(tmp_path / "data"))
    lp.command("initialise")
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.wait_cycles(300)
    lp.command("stop")
    lp.wait_state("STOPPED")
    lp.command("reset")  # initialise again: idempotent logger, no second header
    lp.wait_state("INITIALISED")
    lp.command("start")
    lp.wait_cycles(50)
    lp.command("stop")
    lp.wait_state("STOPPED")
    lp.command("quit")
    code, _ = lp.finish()
    assert code == 0
    files = list((tmp_path / "data" / "logs").glob("probe_*.xrf"))
    assert len(files) == 1
    raw = files[0].read_bytes()
    assert raw[:8] == MAGIC
    jlen, stride = struct.unpack_from("<II", raw, 8)
    header = json.loads(raw[16 : 16 + jlen])
    assert raw.count(MAGIC) == 1
    assert [v["name"] for v in header["variables"]] == ["cycle", "flag", "letter", "count", "ratio", "value"]
    assert header["record_size"] == 8 + 1 + 1 + 4 + 4 + 8 and header["cycle_freq"] == 1000
    off = (16 + jlen + 7) // 8 * 8
    n = (len(raw) - off) // stride
    assert n >= 350
    seqs = []
    for i in range(n):
        seq, cycle, t_ns = struct.unpack_from("<QQq", raw, off + i * stride)
        c, flag, letter, count, ratio, value = struct.unpack_from("<q?cifd", raw, off + i * stride + 24)
        assert c == count and flag == bool(c & 1) and letter == bytes([97 + c % 26])
        assert ratio == c * 0.5 and value == c * 0.25
        seqs.append(seq)
    assert seqs == list(range(n))
    assert lp.ch.status().log_lost == 0


def test_each_sender_learns_its_own_commands_fate(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    # Three commands queued back to back: the loop takes one per cycle. The first is accepted
    # even though a later one is rejected before anybody reads the status.
    t1 = lp.ch.send_command("initialise")
    t2 = lp.ch.send_command(99)
    t3 = lp.ch.send_command("quit")
    r3 = lp.ch.wait_command(t3)
    r1, r2 = lp.ch.wait_command(t1), lp.ch.wait_command(t2)
    assert r1.accepted and r1.reason == ""
    assert not r2.accepted and "99 is not a command" in r2.reason
    assert not r3.accepted and "quit is not allowed" in r3.reason


def _may_use_fifo(prio: int) -> bool:
    import os
    import resource

    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= prio


def test_a_short_main_gets_real_time_scheduling_by_default(run_loop, probe_exe):
    lp = run_loop(probe_exe)
    info = lp.ch.info
    if _may_use_fifo(80):
        assert info["rt_sched"] == 1 and info["priority"] == 80
    else:
        # A safe stop, then the loop's whole output (stop() kills it and drops the output).
        lp.proc.send_signal(signal.SIGINT)
        code, out = lp.finish()
        assert info["rt_sched"] == 0 and "WARNING: real-time scheduling" in out
        assert code == 0, out


def test_xrf_prio_zero_keeps_the_policy_main_chose(run_loop, probe_exe):
    lp = run_loop(probe_exe, XRF_PRIO="0")
    assert lp.ch.info["rt_sched"] == 0 and lp.ch.info["priority"] == 0
