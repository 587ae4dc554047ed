"""The channels binding: ring properties, the command table, histograms, and the Channels class.

Rings are exercised through the cffi binding of rt_core's own channels.c, so these are tests of
the code the loop runs, not of a Python model of it.
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from xrf_testing.testloop import LoopSide, create_for_test
from xrflab import channels, msgdef
from xrflab.channels import Channels, ChannelsError, CommandRingFull, ffi, lib

PAYLOAD_WORDS = 4
SLOT_SIZE = ffi.sizeof("struct xrf_slot_hdr") + 8 * PAYLOAD_WORDS


def pattern(n: int) -> list[int]:
    """Payload of publication n: every word depends on n, so a torn copy cannot pass."""
    return [((n + 1) * 0x9E3779B97F4A7C15 + j) & 0xFFFFFFFFFFFFFFFF for j in range(PAYLOAD_WORDS)]


class SlotRing:
    """A small ring of patterned slots over the binding's xrf_ring operations."""

    def __init__(self, nslots: int) -> None:
        self.ring = ffi.new("struct xrf_ring *")
        self.slots = ffi.new("uint64_t[]", nslots * SLOT_SIZE // 8)  # 8-byte aligned storage
        lib.xrf_ring_init(self.ring, nslots, SLOT_SIZE)
        # The reader's own copy of the geometry, as a host takes it at attach.
        self.geom = ffi.new("struct xrf_ring_geom *")
        assert lib.xrf_ring_geom_check(self.ring, nslots, SLOT_SIZE, nslots * SLOT_SIZE, self.geom) == 0

    def slot_words(self, slot) -> tuple[int, int, list[int]]:
        """(seq, cycle, payload) of a slot pointer."""
        words = ffi.cast("uint64_t *", slot)
        return words[0], words[1], [words[3 + j] for j in range(PAYLOAD_WORDS)]

    def fill(self, slot, n: int) -> None:
        words = ffi.cast("uint64_t *", slot)
        words[1] = n  # hdr.cycle
        for j, w in enumerate(pattern(n)):
            words[3 + j] = w


# ---- broadcast ring -----------------------------------------------------------------------------


class BroadcastReader:
    def __init__(self, ring: SlotRing) -> None:
        self.ring = ring
        self.cursor = ffi.new("uint64_t *", 0)
        self.lost = ffi.new("uint64_t *", 0)
        self.out = ffi.new("uint64_t[]", SLOT_SIZE // 8)

    def drain(self) -> list[tuple[int, list[int]]]:
        got = []
        while (
            lib.xrf_bcast_read_g(self.ring.ring, self.ring.geom, self.ring.slots, self.cursor, self.out, self.lost) == 1
        ):
            _seq, cycle, payload = self.ring.slot_words(self.out)
            got.append((cycle, payload))
        return got


@settings(max_examples=150, deadline=None)
@given(
    nslots=st.sampled_from([1, 2, 4, 8, 16]),
    ops=st.lists(st.tuples(st.sampled_from(["publish", "read_a", "read_b"]), st.integers(0, 40)), max_size=40),
)
def test_broadcast_ring_no_tear_exact_loss_and_wraparound(nslots: int, ops) -> None:
    ring = SlotRing(nslots)
    readers = {"read_a": BroadcastReader(ring), "read_b": BroadcastReader(ring)}
    model_cursor = {"read_a": 0, "read_b": 0}
    model_lost = {"read_a": 0, "read_b": 0}
    published = 0
    for op, n in ops:
        if op == "publish":
            for _ in range(n):
                slot = lib.xrf_bcast_begin(ring.ring, ring.slots)
                ring.fill(slot, published)
                lib.xrf_bcast_commit(ring.ring, slot)
                published += 1
            continue
        reader = readers[op]
        # The model: what is older than the last nslots publications is gone, and counted.
        start = max(model_cursor[op], published - nslots)
        model_lost[op] += start - model_cursor[op]
        got = reader.drain()
        assert [cycle for cycle, _ in got] == list(range(start, published))
        for cycle, payload in got:
            assert payload == pattern(cycle), "torn or stale payload"
        model_cursor[op] = published
        assert reader.lost[0] == model_lost[op]
        assert reader.cursor[0] == published
    assert ring.ring.head == published


def test_broadcast_reader_on_empty_ring_reads_nothing() -> None:
    reader = BroadcastReader(SlotRing(4))
    assert reader.drain() == [] and reader.lost[0] == 0


# ---- command ring -------------------------------------------------------------------------------


def fresh_shm():
    """A zeroed, initialised shm struct in process memory (calloc'd pages: cheap per example)."""
    shm = ffi.new("struct xrf_shm *")
    lib.xrf_shm_init(shm)
    return shm


@settings(max_examples=100, deadline=None)
@given(ops=st.lists(st.tuples(st.sampled_from(["send", "poll"]), st.integers(1, 80)), max_size=20))
def test_command_ring_fifo_tickets_and_full(ops) -> None:
    shm = fresh_shm()
    ring = ffi.addressof(shm, "cmd")
    queue: list[tuple[int, int]] = []
    next_ticket = 1
    slot = ffi.new("struct xrf_cmd_slot *")
    for op, n in ops:
        for _ in range(n):
            if op == "send":
                cmd = next_ticket % 9 - 1  # any int32 goes through; the loop judges it
                ticket = lib.xrf_cmd_send(ring, cmd, lib.XRF_SOURCE_CLI, 1000 + next_ticket)
                if len(queue) == lib.XRF_CMD_SLOTS:
                    assert ticket == -errno.EAGAIN
                else:
                    assert ticket == next_ticket
                    queue.append((ticket, cmd))
                    next_ticket += 1
            else:
                taken = lib.xrf_cmd_poll(ring, slot)
                if not queue:
                    assert taken == 0
                    continue
                assert taken == 1
                ticket, cmd = queue.pop(0)
                assert (slot.ticket, slot.cmd, slot.source, slot.t_sent_ns) == (
                    ticket,
                    cmd,
                    lib.XRF_SOURCE_CLI,
                    1000 + ticket,
                )


def test_channels_send_command_on_full_ring_raises(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        tickets = [ch.send_command("start") for _ in range(lib.XRF_CMD_SLOTS)]
        assert tickets == list(range(1, lib.XRF_CMD_SLOTS + 1))
        with pytest.raises(CommandRingFull, match="not taking commands"):
            ch.send_command("start")


# ---- SPSC ring ----------------------------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(
    nslots=st.sampled_from([1, 2, 4, 8]),
    ops=st.lists(st.tuples(st.sampled_from(["produce", "consume"]), st.integers(0, 20)), max_size=30),
)
def test_spsc_no_loss_until_full_and_dropped_counted(nslots: int, ops) -> None:
    ring = SlotRing(nslots)
    queue: list[int] = []
    produced = dropped = 0
    tail = ffi.new("uint64_t *", 0)  # the consumer's own position
    first = ffi.new("void **")
    for op, n in ops:
        for _ in range(n):
            if op == "produce":
                slot = lib.xrf_spsc_begin(ring.ring, ring.slots)
                if len(queue) == nslots:
                    assert slot == ffi.NULL
                    dropped += 1
                else:
                    assert slot != ffi.NULL
                    ring.fill(slot, produced)
                    lib.xrf_spsc_commit(ring.ring, slot)
                    queue.append(produced)
                produced += 1
            else:
                ready = lib.xrf_spsc_peek_run_g(ring.ring, ring.geom, ring.slots, tail[0], first)
                if not queue:
                    assert ready == 0 and first[0] == ffi.NULL
                    continue
                assert 1 <= ready <= len(queue)
                _seq, cycle, payload = ring.slot_words(first[0])
                expected = queue.pop(0)
                assert cycle == expected and payload == pattern(expected)
                lib.xrf_spsc_release_g(ring.ring, tail, 1)
        assert ring.ring.dropped == dropped
    assert ring.ring.head - ring.ring.tail == len(queue)


@given(record_size=st.integers(0, 4096), ring_bytes=st.integers(0, 1 << 23))
def test_log_slots_for_fits_the_ring(record_size: int, ring_bytes: int) -> None:
    slot_size = ffi.new("uint32_t *")
    n = lib.xrf_log_slots_for(record_size, ring_bytes, slot_size)
    assert slot_size[0] % 8 == 0 and slot_size[0] >= ffi.sizeof("struct xrf_slot_hdr") + record_size
    assert n * slot_size[0] <= ring_bytes
    assert n == 0 or (n & (n - 1)) == 0
    assert n == 0 or 2 * n * slot_size[0] > ring_bytes  # the largest power of two that fits


def test_ros2xeno_latest_wins() -> None:
    shm = fresh_shm()
    data = ffi.addressof(shm, "ros2xeno")
    last_seq = ffi.new("uint32_t *", 0)
    out = ffi.new("uint8_t[16]")
    t_sent = ffi.new("int64_t *")
    assert lib.xrf_data_in_try_read(data, last_seq, out, 16, t_sent) == 0
    for i in range(3):
        assert lib.xrf_data_in_write(data, bytes([i]) * 16, 16, 100 + i) == 0
    assert lib.xrf_data_in_try_read(data, last_seq, out, 16, t_sent) == 1
    assert bytes(out) == bytes([2]) * 16 and t_sent[0] == 102
    assert lib.xrf_data_in_try_read(data, last_seq, out, 16, t_sent) == 0
    assert lib.xrf_data_in_write(data, b"x" * (lib.XRF_MSG_MAX + 1), lib.XRF_MSG_MAX + 1, 0) == -errno.EMSGSIZE


# ---- command table ------------------------------------------------------------------------------

S = {name: getattr(lib, f"XRF_STATE_{name}") for name in channels.STATE_NUMBERS}
# The table of XRF2_API.md, with the decision of architecture.md: reset is allowed from PAUSED.
EXPECTED_TRANSITIONS = {
    1: {"IDLE": "INITIALISING"},
    2: {"INITIALISED": "RUN", "PAUSED": "RUN"},
    3: {"RUN": "STOPPING", "PAUSED": "STOPPING"},
    4: {"RUN": "INITIALISING", "STOPPED": "INITIALISING", "ERROR": "INITIALISING", "PAUSED": "INITIALISING"},
    5: {"RUN": "PAUSING"},
    6: {"STOPPED": "QUIT", "ERROR": "QUIT"},
}
INVALID_COMMANDS = [0, 7, -1, 2**31 - 1, -(2**31)]
ALL_STATES = list(range(1, 11))


@pytest.mark.parametrize("state", ALL_STATES)
@pytest.mark.parametrize("cmd", [1, 2, 3, 4, 5, 6, *INVALID_COMMANDS])
def test_command_table(state: int, cmd: int) -> None:
    name = channels.state_name(state)
    result = lib.xrf_cmd_transition(state, cmd)
    reason = ffi.new("char[]", lib.XRF_REASON_MAX)
    lib.xrf_cmd_reject_reason(state, cmd, reason, lib.XRF_REASON_MAX)
    if cmd not in EXPECTED_TRANSITIONS:
        assert result == -lib.XRF_REJECT_UNKNOWN
        assert f"{cmd} is not a command" in ffi.string(reason).decode()
        return
    target = EXPECTED_TRANSITIONS[cmd].get(name)
    if target is None:
        assert result == -lib.XRF_REJECT_NOT_ALLOWED
        text = ffi.string(reason).decode()
        assert f"not allowed in state {name}" in text
        for allowed in channels.allowed_commands(state):
            assert allowed in text.split("allowed:")[1]
    else:
        assert result == S[target]


def test_allowed_commands_per_state() -> None:
    for state in ALL_STATES:
        name = channels.state_name(state)
        expected = [channels.command_name(c) for c, table in EXPECTED_TRANSITIONS.items() if name in table]
        assert channels.allowed_commands(state) == expected
    assert channels.allowed_commands(lib.XRF_STATE_PAUSED) == ["start", "stop", "reset"]


def test_command_table_through_channels(shm_name: str) -> None:
    """Every (state, command) pair end to end: Channels -> ring -> loop side -> status -> result."""
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        for state in ALL_STATES:
            for cmd in [1, 2, 3, 4, 5, 6, *INVALID_COMMANDS]:
                loop.set_state(state)
                ticket = ch.send_command(cmd)
                loop.handle_commands()
                result = ch.wait_command(ticket, timeout=1)
                target = EXPECTED_TRANSITIONS.get(cmd, {}).get(channels.state_name(state))
                assert result.accepted == (target is not None), (state, cmd, result)
                if target:
                    assert result.state_name == target and result.reason == ""
                else:
                    assert result.state == state and result.reason
                    status = ch.status()
                    assert status.last_rejected_cmd == cmd
                    expected_code = lib.XRF_REJECT_UNKNOWN if cmd in INVALID_COMMANDS else lib.XRF_REJECT_NOT_ALLOWED
                    assert status.reject_code == expected_code


def test_command_names() -> None:
    assert channels.command_number("Start") == 2
    assert channels.command_number(" 7 ") == 7
    assert channels.command_number(-1) == -1
    with pytest.raises(ValueError, match="initialise, start, stop, reset, pause, quit"):
        channels.command_number("jump")


# ---- histograms ---------------------------------------------------------------------------------

LAST_BUCKET = lib.XRF_HIST_BUCKETS - 1


def test_histogram_bucket_edges_are_strictly_monotonic() -> None:
    edges = [lib.xrf_hist_bucket_low(b) for b in range(lib.XRF_HIST_BUCKETS)]
    assert edges[0] == 0
    assert all(a < b for a, b in zip(edges, edges[1:]))
    assert all(lib.xrf_hist_bucket(edge) == b for b, edge in enumerate(edges))


def test_bucket_at_the_edges_of_the_one_compare_path() -> None:
    # hist_inline.h: one compare for 32 <= ns < 2^35 (the last whole octave ends in the last
    # bucket), the linear buckets and the clamp apart.
    assert [lib.xrf_hist_bucket(ns) for ns in (0, 31, 32, 33, 34)] == [0, 31, 32, 32, 33]
    assert lib.xrf_hist_bucket(2**34 - 1) == LAST_BUCKET - 16
    assert lib.xrf_hist_bucket(2**34) == LAST_BUCKET - 15
    assert [lib.xrf_hist_bucket(ns) for ns in (2**35 - 1, 2**35, 2**64 - 1)] == [LAST_BUCKET] * 3


@given(st.one_of(st.integers(0, 10_000), st.integers(0, 2**40), st.integers(0, 2**64 - 1)))
def test_value_falls_in_its_bucket_with_6_percent_resolution(ns: int) -> None:
    b = lib.xrf_hist_bucket(ns)
    assert 0 <= b <= LAST_BUCKET
    low = lib.xrf_hist_bucket_low(b)
    assert low <= ns
    if b < LAST_BUCKET:
        high = lib.xrf_hist_bucket_low(b + 1)
        assert ns < high
        if ns >= 32:
            assert (high - low) / low <= 1 / 16  # 6.25 %: 16 sub-buckets per power of two
        else:
            assert high - low == 1  # exact below 32 ns


def test_histograms_from_status(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        samples = [1000] * 90 + [50_000] * 10
        for ns in samples:
            loop.add_timing("fpga", ns)
        hist = ch.histograms()
        assert list(hist) == ["wakeup", "fpga", "data", "cmd", "monitor", "hook", "logger", "cycle"]
        fpga = hist["fpga"]
        assert (fpga.count, fpga.min, fpga.max) == (100, 1000, 50_000)
        assert fpga.mean == pytest.approx(sum(samples) / 100)
        assert sum(fpga.counts) == 100 and len(fpga.edges) == 2
        assert fpga.percentile(50) <= 1000 < fpga.percentile(50) * 1.07
        assert 50_000 / 1.07 < fpga.percentile(99) <= 50_000
        assert fpga.percentile(100) <= 50_000
        assert hist["cycle"].count == 0 and hist["cycle"].percentile(99) == 0


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.lists(st.tuples(st.integers(0, channels.lib.XRF_HIST_BUCKETS - 1), st.integers(0, 1000)), max_size=12),
        min_size=8,
        max_size=8,
    ),
    st.lists(st.integers(-5, 5), min_size=8, max_size=8),
)
def test_stage_figures_are_what_each_histogram_says(stages, count_skew) -> None:
    # The timing series' figures from one status copy, all stages at once (status.stage_figures_of),
    # against each stage's Histogram: percentiles, count, sum, min and max the same, also where the
    # count does not add up to the buckets (a loop may write anything there).
    from xrflab.channels.status import hist_words, histogram_from_struct, stage_figures_of

    s = ffi.new("struct xrf_status *")
    for i, buckets in enumerate(stages):
        h = s.hist[i]
        for b, n in buckets:
            h.buckets[b] += n
        total = sum(n for _, n in buckets)
        h.count = max(0, total + count_skew[i])
        h.sum_ns = 1234 * total
        h.min_ns = lib.xrf_hist_bucket_low(min((b for b, n in buckets if n), default=0))
        h.max_ns = lib.xrf_hist_bucket_low(max((b for b, n in buckets if n), default=0)) + 7
    ps = (0.0, 1.0, 50.0, 90.0, 99.0, 99.9, 100.0)
    figures = stage_figures_of(hist_words(s), ps)
    assert len(figures) == len(channels.STAGE_NAMES)
    for i, f in enumerate(figures):
        h = histogram_from_struct(s.hist[i])
        assert f.percentiles == tuple(h.percentile(p) for p in ps)
        assert (f.count, f.max_ns) == (h.count, h.max)
        assert f.min_ns == h.min and f.sum_ns == s.hist[i].sum_ns


_HIST_WORD_COUNT = len(channels.STAGE_NAMES) * (4 + lib.XRF_HIST_BUCKETS)


@settings(max_examples=30, deadline=None)
@given(
    st.lists(
        st.lists(st.tuples(st.integers(0, _HIST_WORD_COUNT - 1), st.integers(0, 1 << 40)), max_size=40),
        min_size=1,
        max_size=5,
    )
)
def test_the_figures_of_several_copies_at_once_are_each_copys_own(copies) -> None:
    # The timing series makes the lines of several samples in one pass (stage_figures_many): each
    # copy's figures are what stage_figures_of gives for it alone, whatever words the loop wrote
    # (any word of any stage: counts, sums, min and max included).
    from xrflab.channels.status import hist_words, stage_figures_many, stage_figures_of

    words = []
    for pokes in copies:
        s = ffi.new("struct xrf_status *")
        w = np.frombuffer(ffi.buffer(s.hist), dtype=np.int64)
        for at, v in pokes:
            w[at] = v
        words.append(hist_words(s))
    ps = (0.0, 50.0, 99.0, 100.0)
    together = stage_figures_many(np.stack(words), ps)
    assert together == [stage_figures_of(w, ps) for w in words]
    assert len(together) == len(copies) and all(len(f) == len(channels.STAGE_NAMES) for f in together)


# ---- the Channels class -------------------------------------------------------------------------


def test_open_checks_and_info(shm_name: str) -> None:
    with create_for_test(shm_name, program="relbot_ctrl") as created:
        with Channels.open(shm_name, wait_s=1) as ch:
            info = ch.info
            assert info["program"] == "relbot_ctrl" and info["backend"] == "posix"
            assert info["ros2xeno_schema"] == "float64 steer_left\nfloat64 steer_right"
            assert info["pid"] == os.getpid() and info["ros2xeno_size"] == 16
            assert ch.status().state_name == "IDLE"
            # create_for_test plays a loop inside loop(): running, so host tools take it as alive
            assert ch.status().running is True and ch.loop_alive()
            LoopSide(created).set_state(channels.lib.XRF_STATE_STOPPED, running=False)
            assert ch.status().running is False and not ch.loop_alive()


def test_open_missing_times_out_with_a_clear_error(shm_name: str) -> None:
    t0 = time.monotonic()
    with pytest.raises(ChannelsError, match="appear"):
        Channels.open(shm_name, wait_s=0.2)
    assert time.monotonic() - t0 < 2


def test_open_rejects_foreign_and_unready_objects(shm_name: str) -> None:
    path = channels.shm_path(shm_name)
    with open(path, "wb") as f:
        f.write(b"JUNK" + bytes(channels.SHM_SIZE - 4))
    with pytest.raises(ChannelsError, match="not an XRF"):
        Channels.open(shm_name, wait_s=0.2)
    path.unlink()
    with create_for_test(shm_name) as ch:
        ch.shm.ready = 0
        with pytest.raises(ChannelsError, match="ready"):
            Channels.open(shm_name, wait_s=0.2)
        ch.shm.ready = 1
        ch.shm.version = lib.XRF_SHM_VERSION + 1
        with pytest.raises(ChannelsError, match="version"):
            Channels.open(shm_name, wait_s=0.2)


def test_open_waits_for_ready(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        ch.shm.ready = 0
        timer = threading.Timer(0.2, lambda: lib.xrf_shm_publish_ready(ch.shm))
        timer.start()
        with Channels.open(shm_name, wait_s=3) as opened:
            assert opened.info["cycle_freq"] == 1000
        timer.join()


def test_write_ros2xeno(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        before = time.monotonic_ns()
        ch.write_ros2xeno({"steer_left": 1.5})
        assert loop.read_ros2xeno() == {"steer_left": 1.5, "steer_right": 0.0}
        assert before <= ch.shm.ros2xeno.t_sent_ns <= time.monotonic_ns()
        with pytest.raises(ValueError, match="valid fields: steer_left, steer_right"):
            ch.write_ros2xeno({"throttle": 1})


def test_telemetry_and_monitor_readers(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        loop.publish_telemetry(0)  # before the reader: not seen
        reader = ch.telemetry_reader()
        early = ch.telemetry_reader(from_start=True)
        loop.publish_telemetry(
            1,
            t_ns=123,
            state=4,
            enc=[1, 2, 3, 4],
            din=[1, 0] * 4,
            pwm=[-5, 5, 0, 409],
            dout=[1, 0, 0, 1],
            xeno2ros={"pos_left": 0.5},
            ros2xeno_t_sent_ns=99,
        )
        [t] = reader.read()
        assert (t.cycle, t.t_ns, t.state, t.enc, t.pwm, t.dout) == (
            1,
            123,
            4,
            [1, 2, 3, 4],
            [-5, 5, 0, 409],
            [1, 0, 0, 1],
        )
        assert t.din == [1, 0] * 4 and t.ros2xeno_t_sent_ns == 99
        assert t.xeno2ros == {"pos_left": 0.5, "pos_right": 0.0}
        assert [x.cycle for x in early.read()] == [0, 1]
        # Lapping: a reader that falls more than a ring behind learns exactly how much it missed.
        for cycle in range(2, 2 + lib.XRF_TELEM_SLOTS + 10):
            loop.publish_telemetry(cycle, ring=False)
        got = reader.read()
        assert reader.lost == 10 and len(got) == lib.XRF_TELEM_SLOTS and got[0].cycle == 12
        assert reader.read(max_items=5) == []

        monitor = ch.monitor_reader()
        loop.publish_monitor(7, "x = 1.00\n")
        loop.publish_monitor(8, "é" * 200)  # cut at the slot's size without breaking the decode
        lines = monitor.read()
        assert lines[0] == channels.MonitorLine(cycle=7, t_ns=lines[0].t_ns, text="x = 1.00\n")
        assert lines[1].cycle == 8 and lines[1].text.startswith("éé")


def test_telemetry_batch_columns_are_its_samples(shm_name: str) -> None:
    """read_batch (the reader's: numpy converts the slots, a sample is made whole only when
    asked for): its columns are exactly the samples' fields, across more slots than one numpy
    chunk, and a payload size the loop wrote beyond the slot is bounded as read() bounds it."""
    from xrflab.channels.rings import BATCH_SLOTS

    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        reader = ch.telemetry_reader()
        check = ch.telemetry_reader()
        n = BATCH_SLOTS * 2 + 3
        for cycle in range(n):
            loop.publish_telemetry(
                cycle,
                t_ns=1000 + cycle,
                enc=[cycle, -cycle, 3, 4],
                din=[cycle & 1, 0] * 4,
                xeno2ros={"pos_left": cycle / 2},
                ring=False,
            )
        batch = reader.read_batch()
        whole = check.read()
        assert len(batch) == n == len(whole)
        assert batch.t_ns == [t.t_ns for t in whole] and batch.cycle == [t.cycle for t in whole]
        assert batch.enc == [t.enc for t in whole] and batch.din == [t.din for t in whole]
        assert list(batch) == whole and batch[-1] == whole[-1] and batch[1:3] == whole[1:3]
        assert batch[n - 1].xeno2ros == {"pos_left": (n - 1) / 2, "pos_right": 0.0}
        with pytest.raises(IndexError):
            batch[n]
        assert len(reader.read_batch()) == 0
        loop.publish_telemetry(n, ring=False)
        slot = ch.shm.telem[n % lib.XRF_TELEM_SLOTS]
        slot.size = 2**32 - 1  # the loop's word: read as at most XRF_MSG_MAX bytes
        [t] = reader.read_batch()
        assert t.cycle == n and t == check.read()[0]


def test_telemetry_sample_is_its_slot_field_by_field(shm_name: str) -> None:
    """A sample read_batch makes (one struct unpack of the slot's bytes, its layout taken from
    cffi's) is the slot as cffi reads it field by field: every channel of every array, values
    at both ends of their types, the payload cut at the size the loop wrote."""
    with create_for_test(shm_name, channels=lib.XRF_MAX_CHANNELS) as ch:
        loop = LoopSide(ch)
        reader = ch.telemetry_reader()
        m = lib.XRF_MAX_CHANNELS
        loop.publish_telemetry(
            2**40 + 3,
            t_ns=2**63 - 5,
            enc=[-(2**31)] + [2**31 - 1 - k for k in range(m - 1)],
            din=[255, 0] * m,
            pwm=[(-1) ** k * (100 + k) for k in range(m)],
            dout=[k & 1 for k in range(m)],
            xeno2ros={"pos_left": -1.5, "pos_right": 2.25},
            state=3,
            ros2xeno_t_sent_ns=2**62 + 1,
        )
        slot = ch.shm.telem[0]  # the ring's first publication
        [t] = reader.read_batch()
        assert (t.cycle, t.t_ns, t.state) == (slot.hdr.cycle, slot.hdr.t_ns, slot.state) == (2**40 + 3, 2**63 - 5, 3)
        assert t.enc == list(slot.enc)[:m] and t.enc[0] == -(2**31)
        assert t.din == list(slot.din)[: 2 * m] and t.din[0] == 255
        assert t.pwm == list(slot.pwm)[:m] and t.pwm[1] == -101
        assert t.dout == list(slot.dout)[:m]
        assert t.ros2xeno_t_sent_ns == slot.ros2xeno_t_sent_ns == 2**62 + 1
        assert t.xeno2ros == {"pos_left": -1.5, "pos_right": 2.25}
        # A payload shorter than the message (the loop's size word): not decoded, nothing made up.
        loop.publish_telemetry(2**40 + 4, xeno2ros={"pos_left": 1.0})
        ch.shm.telem[1].size = 3
        [t] = reader.read_batch()
        assert t.cycle == 2**40 + 4 and t.xeno2ros == {}


def test_telemetry_follows_the_benchs_channel_count(shm_name: str) -> None:
    """A bench of more than one board (the youBot's 9 channels): telemetry carries them all, and
    only them; a count the loop wrote out of range is refused at open (issue 29 item 2)."""
    nine = 9
    assert lib.XRF_ICO_CHANNELS < nine <= lib.XRF_MAX_CHANNELS
    with create_for_test(shm_name, channels=nine) as ch:
        assert ch.geom.channels == nine
        loop = LoopSide(ch)
        reader = ch.telemetry_reader()
        loop.publish_telemetry(
            1,
            enc=list(range(1, lib.XRF_MAX_CHANNELS + 1)),
            din=[1] * (2 * lib.XRF_MAX_CHANNELS),
            pwm=[-100 * k for k in range(lib.XRF_MAX_CHANNELS)],
            dout=[1] * lib.XRF_MAX_CHANNELS,
        )
        [t] = reader.read()
        assert t.enc == list(range(1, nine + 1)) and t.pwm == [-100 * k for k in range(nine)]
        assert t.din == [1] * (2 * nine) and t.dout == [1] * nine
        # The loop rewriting the count after open changes nothing for this reader.
        ch.shm.channels = 1000
        loop.publish_telemetry(2, enc=[7] * lib.XRF_MAX_CHANNELS)
        [t] = reader.read()
        assert t.enc == [7] * nine
    (Path("/dev/shm") / shm_name).unlink()
    for hostile in (0, lib.XRF_MAX_CHANNELS + 1, 2**32 - 1):
        with pytest.raises(channels.ChannelsCorrupt):
            create_for_test(shm_name, channels=hostile)
        (Path("/dev/shm") / shm_name).unlink()


def test_doorbell_wakes_a_waiting_host(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        seen = ch.doorbell
        threading.Timer(0.1, lambda: loop.publish_monitor(1, "ring")).start()
        t0 = time.monotonic()
        assert ch.wait_doorbell(seen, 5000) != seen
        assert time.monotonic() - t0 < 2
        t0 = time.monotonic()
        assert ch.wait_doorbell(ch.doorbell, 50) == ch.doorbell  # nothing published: times out
        assert time.monotonic() - t0 >= 0.04


def test_heartbeat_timeout_and_sim_outputs(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        ch.configure_host_timeout(250, "stop")
        assert (ch.shm.host_timeout_ms, ch.shm.host_timeout_action) == (250, lib.XRF_HOST_LOST_ACTION_STOP)
        first = ch.shm.host_heartbeat_ns
        ch.host_heartbeat()
        assert ch.shm.host_heartbeat_ns >= first > 0
        ch.force_sim_outputs_off()
        assert ch.shm.sim.forced_off == 1


def test_wait_command_times_out_without_a_loop(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        ticket = ch.send_command("initialise")
        with pytest.raises(channels.CommandTimeout, match="not handled"):
            ch.wait_command(ticket, timeout=0.05)


def test_msgdef_limit_matches_channels_h() -> None:
    assert msgdef.MSG_MAX_BYTES == lib.XRF_MSG_MAX


def test_binding_is_cached_by_source_hash(tmp_path: Path, monkeypatch) -> None:
    from xrflab import _cffi_build

    monkeypatch.setenv("XRF_CACHE_DIR", str(tmp_path))
    target = _cffi_build.cache_dir()
    assert target.parent == tmp_path and len(target.name) == 16
    assert "struct xrf_shm" in _cffi_build.extract_cdef(
        (_cffi_build.rt_core_dir() / "include" / "xrf" / "channels.h").read_text()
    )


# ---- concurrency in C ---------------------------------------------------------------------------


def test_rings_stress_in_c(repo_root: Path, tmp_path: Path) -> None:
    """Builds and runs rt_core/tests/test_rings_stress.c (producer and consumer threads)."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    assert compiler, "a C compiler is needed (build-essential)"
    exe = tmp_path / "test_rings_stress"
    subprocess.run(
        [
            compiler,
            "-O2",
            "-std=gnu11",
            "-Wall",
            "-Werror",
            "-pthread",
            "-I",
            str(repo_root / "rt_core" / "include"),
            str(repo_root / "rt_core" / "src" / "channels.c"),
            str(repo_root / "rt_core" / "src" / "logformat.c"),  # the log type table (xrf_log_meta_check)
            str(repo_root / "rt_core" / "tests" / "test_rings_stress.c"),
            "-o",
            str(exe),
        ],
        check=True,
    )
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.strip().splitlines()[-1].endswith(" passed, 0 failed")


def test_host_lost_actions_are_channels_h_list() -> None:
    """The names the appliance sends (XRF_HOST_TIMEOUT_ACTION) are the ones the runtime parses:
    both come from channels.h's XRF_HOST_LOST_ACTIONS; the numbers are the segment's."""
    assert channels.HOST_LOST_ACTIONS == {"ignore": 0, "pause": 1, "stop": 2}
    for name, number in channels.HOST_LOST_ACTIONS.items():
        assert lib.xrf_host_lost_action_parse(name.encode()) == number
    assert lib.xrf_host_lost_action_parse(b"halt") == -errno.EINVAL
    assert lib.xrf_host_lost_action_name(len(channels.HOST_LOST_ACTIONS)) == ffi.NULL
