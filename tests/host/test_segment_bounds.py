"""What a reader does with a hostile segment (issue 26, docs/developers/security.md "The shared
segment"): rt_core's host-side checks (xrf_shm_check, xrf_ring_geom_check, xrf_log_meta_check)
and bounded readers (xrf_bcast_read_g, xrf_spsc_peek_run_g, xrf_cmd_send, xrf_status_read),
through the binding, and the Python side over them (Channels, the rings, LogChannel and the host
log writer): every geometry, head, tail, layout and schema a loop could write is refused with
-EPROTO / ChannelsCorrupt or bounded, never used to address memory. The libFuzzer harness
(branch i26-fuzz) drives the same C functions over arbitrary bytes."""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from xrf_testing.testloop import LoopSide, create_for_test
from xrflab import channels
from xrflab.channels import Channels, ChannelsCorrupt, ChannelsError, ffi, lib, segment
from xrflab.logs.host_writer import HostLogWriter
from xrflab.logs.log_channel import LogChannel
from xrflab.logs.reader import open_log

HDR = ffi.sizeof("struct xrf_slot_hdr")
SHM_SIZE = ffi.sizeof("struct xrf_shm")
TELEM = ffi.sizeof("struct xrf_telemetry")
MONITOR = ffi.sizeof("struct xrf_monitor_line")
LOG_BYTES = lib.XRF_LOG_RING_BYTES


def fresh_shm():  # noqa: ANN201 - cdata
    shm = ffi.new("struct xrf_shm *")
    lib.xrf_shm_init(shm)
    return shm


# ---- geometry at attach ---------------------------------------------------------------------------


def test_ring_geometry_is_checked_against_the_space_and_the_header() -> None:
    r = ffi.new("struct xrf_ring *")
    g = ffi.new("struct xrf_ring_geom *")
    lib.xrf_ring_init(r, 16, 64)
    assert lib.xrf_ring_geom_check(r, 16, 64, 16 * 64, g) == 0 and (g.slots, g.slot_size) == (16, 64)
    # What the reader asks for must itself be a ring inside its space.
    for slots, size, cap in ((0, 64, 4096), (12, 64, 4096), (16, 60, 4096), (16, 16, 4096), (16, 64, 16 * 64 - 1)):
        assert lib.xrf_ring_geom_check(r, slots, size, cap, g) == -errno.EINVAL, (slots, size, cap)
    # What the loop says must be the same.
    r.slots = 1 << 31
    assert lib.xrf_ring_geom_check(r, 16, 64, 16 * 64, g) == -errno.EPROTO
    r.slots, r.slot_size = 16, 0xFFFFFFF8
    assert lib.xrf_ring_geom_check(r, 16, 64, 16 * 64, g) == -errno.EPROTO


def test_shm_check_refuses_a_short_mapping_a_foreign_header_and_a_moved_ring() -> None:
    shm = fresh_shm()
    g = ffi.new("struct xrf_shm_geom *")
    assert lib.xrf_shm_check(shm, SHM_SIZE, g) == 0
    assert (g.telem.slots, g.telem.slot_size) == (lib.XRF_TELEM_SLOTS, TELEM)
    assert (g.monitor.slots, g.monitor.slot_size) == (lib.XRF_MONITOR_SLOTS, MONITOR)
    assert lib.xrf_shm_check(shm, SHM_SIZE - 1, g) == -errno.EINVAL
    for field, value in (("magic", 0), ("version", 99), ("size", 12)):
        bad = fresh_shm()
        setattr(bad, field, value)
        assert lib.xrf_shm_check(bad, SHM_SIZE, g) == -errno.EPROTO, field
    bad = fresh_shm()
    bad.monitor_ring.slots, bad.monitor_ring.slot_size = 1 << 31, 0xFFFFFFF8  # issue 26, hole 4
    assert lib.xrf_shm_check(bad, SHM_SIZE, g) == -errno.EPROTO


def test_channels_refuse_a_segment_whose_rings_or_info_are_not_the_runtimes(shm_name: str) -> None:
    def broken(change) -> str:  # noqa: ANN001
        c = create_for_test(shm_name)
        try:
            change(c.shm)
            with pytest.raises(ChannelsCorrupt) as exc:
                Channels.open(shm_name, wait_s=0.2)  # a new reader, as the appliance opens a run
            return str(exc.value)
        finally:
            c.close()
            channels.shm_path(shm_name).unlink(missing_ok=True)

    def ring(shm) -> None:  # noqa: ANN001
        shm.telem_ring.slot_size = 8

    def freq(shm) -> None:  # noqa: ANN001
        shm.info.cycle_freq = 0

    def priority(shm) -> None:  # noqa: ANN001
        shm.info.priority = 150

    def schema(shm) -> None:  # noqa: ANN001
        shm.info.xeno2ros_schema = b"float64[99999] big"

    assert "ring geometry" in broken(ring)
    assert "cycle_freq" in broken(freq)
    assert "priority" in broken(priority)
    assert "xeno2ros schema" in broken(schema)


def test_channels_copy_what_is_constant_at_open(ch: Channels) -> None:
    info = dict(ch.info)
    codec = ch.xeno2ros_codec
    ch.shm.info.cycle_freq = 0
    ch.shm.info.program = b"x" * 63
    ch.shm.info.xeno2ros_schema = b"garbage"
    assert ch.info == info and ch.xeno2ros_codec is codec


# ---- broadcast rings ----------------------------------------------------------------------------


def test_broadcast_reader_refuses_a_moved_ring_and_a_head_going_back(ch: Channels) -> None:
    loop = LoopSide(ch)
    reader = ch.monitor_reader()
    loop.publish_monitor(1, "hello")
    assert [m.text for m in reader.read()] == ["hello"]
    # Hole 4: the loop's ring now says 2^31 slots of 4 GiB. The reader's geometry is its own.
    ch.shm.monitor_ring.slots, ch.shm.monitor_ring.slot_size = 1 << 31, 0xFFFFFFF8
    with pytest.raises(ChannelsCorrupt, match="went back|ring"):
        reader.read()
    ch.shm.monitor_ring.slots, ch.shm.monitor_ring.slot_size = lib.XRF_MONITOR_SLOTS, MONITOR
    assert reader.read() == []
    ch.shm.monitor_ring.head = 0  # publications are never taken back
    with pytest.raises(ChannelsCorrupt):
        reader.read()


def test_broadcast_reader_bounds_a_head_far_ahead(ch: Channels) -> None:
    telemetry = ch.telemetry_reader()
    ch.shm.telem_ring.head = 1 << 62  # slots whose seq does not match: skipped, counted, bounded
    t0 = time.monotonic()
    assert telemetry.read() == []
    assert time.monotonic() - t0 < 2.0
    assert telemetry.lost >= (1 << 62) - lib.XRF_TELEM_SLOTS


@settings(max_examples=200, deadline=None)
@given(
    head=st.integers(0, 2**64 - 1),
    cursor=st.integers(0, 2**64 - 1),
    slots=st.sampled_from([0, 1, 3, 4, 1 << 31, 2**32 - 1]),
    slot_size=st.sampled_from([0, 8, 24, 48, 0xFFFFFFF8]),
    seqs=st.lists(st.integers(0, 2**64 - 1), min_size=4, max_size=4),
)
def test_bcast_read_g_never_leaves_its_ring(
    head: int, cursor: int, slots: int, slot_size: int, seqs: list[int]
) -> None:
    """Whatever the loop writes in the header and the slots' seqs: 1, 0 or -EPROTO, and only the
    reader's 4 x 48 bytes are ever read (ASan in the fuzz harness checks the same in C)."""
    r = ffi.new("struct xrf_ring *")
    lib.xrf_ring_init(r, 4, 48)
    g = ffi.new("struct xrf_ring_geom *")
    assert lib.xrf_ring_geom_check(r, 4, 48, 4 * 48, g) == 0
    buf = ffi.new("uint64_t[]", 4 * 6)
    for i, s in enumerate(seqs):
        buf[i * 6] = s
    r.head, r.slots, r.slot_size = head, slots, slot_size
    c = ffi.new("uint64_t *", cursor)
    lost = ffi.new("uint64_t *", 0)
    out = ffi.new("uint64_t[6]")
    rc = lib.xrf_bcast_read_g(r, g, buf, c, out, lost)
    assert rc in (0, 1, -errno.EPROTO)
    if (slots, slot_size) != (4, 48) or cursor > head:
        assert rc == -errno.EPROTO


# ---- the log ring (hole 3) ----------------------------------------------------------------------


def publish_log(shm, variables: list[tuple[str, int]], writer: int = lib.XRF_LOG_WRITER_HOST, path: bytes = b"log.xrf"):  # noqa: ANN001, ANN201
    """As XenoFrtLogger::publish does: packed variables, the ring sized by xrf_log_slots_for."""
    m = shm.log_meta
    offset = 0
    for i, (name, code) in enumerate(variables):
        m.vars[i].name = name.encode()
        m.vars[i].type = code
        m.vars[i].offset = offset
        offset += lib.xrf_logfile_type_of(code).size
    m.nvars, m.record_size, m.writer, m.path, m.file_mode = len(variables), offset, writer, path, 0o640
    size = ffi.new("uint32_t *")
    slots = lib.xrf_log_slots_for(offset, LOG_BYTES, size)
    lib.xrf_ring_init(ffi.addressof(shm, "log_ring"), slots, size[0])
    m.generation += 1
    m.ready = 1
    return slots, size[0]


def take(shm) -> tuple[int, object, object, int]:  # noqa: ANN001
    out = ffi.new("struct xrf_log_meta *")
    g = ffi.new("struct xrf_ring_geom *")
    tail = ffi.new("uint64_t *")
    rc = lib.xrf_log_meta_check(ffi.addressof(shm, "log_meta"), ffi.addressof(shm, "log_ring"), LOG_BYTES, out, g, tail)
    return rc, out, g, tail[0]


def test_log_meta_check_takes_what_a_logger_publishes() -> None:
    shm = fresh_shm()
    assert take(shm)[0] == -errno.EAGAIN  # not ready
    slots, size = publish_log(shm, [("a", lib.XRF_LOG_DOUBLE), ("b", lib.XRF_LOG_INT), ("c", lib.XRF_LOG_BOOL)])
    shm.log_ring.tail = 7
    rc, out, g, tail = take(shm)
    assert rc == 0 and (g.slots, g.slot_size, tail) == (slots, size, 7)
    assert out.nvars == 3 and out.record_size == 13 and out.generation == 1
    # The copy is ours: what the loop writes afterwards does not reach it.
    shm.log_meta.nvars = 10_000
    assert out.nvars == 3


@pytest.mark.parametrize(
    "what",
    [
        "nvars",
        "type",
        "offset_past_record",
        "negative_offset",
        "name_unterminated",
        "path_unterminated",
        "writer",
        "record_size",
        "ring_slots",
        "ring_slot_size",
        "issue_26_exploit",
    ],
)
def test_log_meta_check_refuses_what_no_logger_publishes(what: str) -> None:
    shm = fresh_shm()
    publish_log(shm, [("a", lib.XRF_LOG_DOUBLE), ("b", lib.XRF_LOG_INT)])
    m, r = shm.log_meta, shm.log_ring
    if what == "nvars":
        m.nvars = lib.XRF_LOG_VARS_MAX + 1
    elif what == "type":
        m.vars[1].type = 77
    elif what == "offset_past_record":
        m.vars[1].offset = m.record_size - 3  # an int needs 4
    elif what == "negative_offset":
        m.vars[0].offset = -8
    elif what == "name_unterminated":
        ffi.memmove(m.vars[0].name, b"n" * lib.XRF_NAME_MAX, lib.XRF_NAME_MAX)
    elif what == "path_unterminated":
        ffi.memmove(m.path, b"p" * lib.XRF_PATH_MAX, lib.XRF_PATH_MAX)
    elif what == "writer":
        m.writer = 7
    elif what == "record_size":
        m.record_size = LOG_BYTES
    elif what == "ring_slots":
        r.slots *= 2
    elif what == "ring_slot_size":
        r.slot_size += 8
    else:  # the student's: a huge record, 1024 slots of 64 KiB, all of them ready
        m.nvars, m.record_size = 1, 65536 - HDR
        r.slots, r.slot_size, r.tail, r.head = 1024, 65536, 0, 1024
    m.generation += 1
    assert take(shm)[0] == -errno.EPROTO


@settings(max_examples=300, deadline=None)
@given(
    data=st.binary(min_size=ffi.sizeof("struct xrf_log_meta"), max_size=ffi.sizeof("struct xrf_log_meta")),
    slots=st.integers(0, 2**32 - 1),
    slot_size=st.integers(0, 2**32 - 1),
)
def test_log_meta_check_on_arbitrary_bytes_keeps_its_promises(data: bytes, slots: int, slot_size: int) -> None:
    shm = fresh_shm()
    ffi.memmove(ffi.addressof(shm, "log_meta"), data, len(data))
    shm.log_meta.ready = 1
    shm.log_ring.slots, shm.log_ring.slot_size = slots, slot_size
    rc, out, g, _ = take(shm)
    assert rc in (0, -errno.EPROTO)
    if rc == 0:  # then everything a writer uses lies inside the ring and the record
        assert g.slots * g.slot_size <= LOG_BYTES and g.slot_size >= HDR + out.record_size
        for i in range(out.nvars):
            v = out.vars[i]
            assert 0 <= v.offset and v.offset + lib.xrf_logfile_type_of(v.type).size <= out.record_size


def test_spsc_peek_run_g_bounds_head_and_tail() -> None:
    r = ffi.new("struct xrf_ring *")
    lib.xrf_ring_init(r, 8, 32)
    g = ffi.new("struct xrf_ring_geom *")
    assert lib.xrf_ring_geom_check(r, 8, 32, 8 * 32, g) == 0
    slots = ffi.new("uint64_t[]", 8 * 4)
    first = ffi.new("void **")
    r.head = 6
    assert lib.xrf_spsc_peek_run_g(r, g, slots, 0, first) == 6
    assert lib.xrf_spsc_peek_run_g(r, g, slots, 5, first) == 1
    r.head = 13
    assert lib.xrf_spsc_peek_run_g(r, g, slots, 6, first) == 2  # to the ring's end: 6, 7
    assert ffi.cast("char *", first[0]) - ffi.cast("char *", slots) == 6 * 32
    r.head = 9 + 8  # more than the ring holds
    assert lib.xrf_spsc_peek_run_g(r, g, slots, 8, first) == -errno.EPROTO and first[0] == ffi.NULL
    r.head = 3  # behind the reader
    assert lib.xrf_spsc_peek_run_g(r, g, slots, 8, first) == -errno.EPROTO
    r.head, r.slot_size = 10, 0xFFFFFFF8
    assert lib.xrf_spsc_peek_run_g(r, g, slots, 8, first) == -errno.EPROTO
    tail = ffi.new("uint64_t *", 8)
    lib.xrf_spsc_release_g(r, tail, 2)
    assert tail[0] == 10 and r.tail == 10


def _host_writer_over(ch: Channels, run_dir: Path) -> tuple[HostLogWriter, list[ChannelsCorrupt]]:
    seen: list[ChannelsCorrupt] = []
    return HostLogWriter(ch, {"run": "1"}, run_dir, timing=False, on_corrupt=seen.append), seen


def _log_records(ch: Channels, n: int, start: int = 0) -> None:
    for k in range(start, start + n):
        slot = lib.xrf_spsc_begin(ffi.addressof(ch.shm, "log_ring"), ch.shm.log_data)
        assert slot != ffi.NULL
        words = ffi.cast("uint64_t *", slot)
        words[0], words[1], words[2] = k, k, k  # seq, cycle, t_ns
        ffi.cast("double *", slot)[3] = k * 0.5
        lib.xrf_spsc_commit(ffi.addressof(ch.shm, "log_ring"), slot)


@pytest.mark.parametrize("attack", ["layout", "head", "head_back"])
def test_host_writer_stops_at_its_last_whole_record(ch: Channels, tmp_path: Path, attack: str) -> None:
    """Hole 3 in one process: the writer drains a good layout, the loop then rewrites it (or its
    ring's head): the file keeps the records written so far and nothing else, the writer says
    so once and reads no more."""
    publish_log(ch.shm, [("x", lib.XRF_LOG_DOUBLE)], path=b"log.xrf")
    w, seen = _host_writer_over(ch, tmp_path)
    _log_records(ch, 50)
    assert w.drain() == 50
    _log_records(ch, 10, 50)
    if attack == "layout":
        m = ch.shm.log_meta
        m.path, m.nvars, m.record_size = b"stolen.bin", 1, 65536 - HDR
        ch.shm.log_ring.slots, ch.shm.log_ring.slot_size, ch.shm.log_ring.head = 1024, 65536, 1 << 20
        m.generation += 1
    elif attack == "head":
        ch.shm.log_ring.head += 1 << 40
    else:
        ch.shm.log_ring.head = 3
    assert w.drain() == 0 and w.drain() == 0
    stats = w.finish()
    assert len(seen) == 1 and w.corrupt
    assert not (tmp_path / "stolen.bin").exists()
    log = open_log(tmp_path / "log.xrf")
    assert list(log.records["seq"]) == list(range(50)) and stats.records == 50 and not log.skipped


def test_a_republished_layout_is_taken_not_refused(ch: Channels, tmp_path: Path) -> None:
    """A logger set up again (a new generation, the ring set up anew) is the protocol, not an
    attack: the writer starts a new segment."""
    publish_log(ch.shm, [("x", lib.XRF_LOG_DOUBLE)])
    w, seen = _host_writer_over(ch, tmp_path)
    _log_records(ch, 5)
    assert w.drain() == 5
    publish_log(ch.shm, [("x", lib.XRF_LOG_DOUBLE), ("y", lib.XRF_LOG_LONG_INT)])
    _log_records(ch, 3, 5)
    assert w.drain() == 3
    w.finish()
    assert not seen and [len(s.records) for s in open_log(tmp_path / "log.xrf").segments] == [5, 3]


def test_a_layout_that_never_settles_is_corrupt(ch: Channels, tmp_path: Path) -> None:
    """Each new generation starts a segment (a header of up to 56 KiB): a loop bumping it at
    every drain is stopped, not given a file of headers."""
    from xrflab.logs.log_channel import MAX_LAYOUTS

    publish_log(ch.shm, [("x", lib.XRF_LOG_DOUBLE)])
    w, seen = _host_writer_over(ch, tmp_path)
    for _ in range(MAX_LAYOUTS + 5):
        ch.shm.log_meta.generation += 1
        w.drain()
    w.finish()
    assert len(seen) == 1 and "changed" in str(seen[0])
    assert len(open_log(tmp_path / "log.xrf").segments) <= MAX_LAYOUTS


def test_log_channel_layout_is_the_checked_copy(ch: Channels) -> None:
    publish_log(ch.shm, [("x", lib.XRF_LOG_DOUBLE)], path=b"a/b.xrf")
    chan = LogChannel(ch, "log")
    layout = chan.take_layout()
    assert layout is not None and layout.path == "a/b.xrf" and layout.stride == chan.slot_size()
    ch.shm.log_meta.path = b"/etc/shadow"
    assert chan.layout().path == "a/b.xrf"


# ---- commands and status --------------------------------------------------------------------------


def test_cmd_send_gives_up_on_slot_seqs_that_never_fit() -> None:
    shm = fresh_shm()
    ring = ffi.addressof(shm, "cmd")
    for i in range(lib.XRF_CMD_SLOTS):
        shm.cmd.slot[i].seq = 1 << 40  # always "ahead": the sender used to spin forever here
    t0 = time.monotonic()
    assert lib.xrf_cmd_send(ring, lib.XRF_CMD_START, lib.XRF_SOURCE_CLI, 0) == -errno.EBUSY
    assert time.monotonic() - t0 < 2.0
    shm.cmd.head = 2**63 - 1
    shm.cmd.slot[(2**63 - 1) % lib.XRF_CMD_SLOTS].seq = 2**63 - 1
    assert lib.xrf_cmd_send(ring, lib.XRF_CMD_START, lib.XRF_SOURCE_CLI, 0) == -errno.EPROTO


def test_commands_on_a_scribbled_ring_are_corrupt_and_a_locked_status_gives_up_quickly(ch: Channels) -> None:
    for i in range(lib.XRF_CMD_SLOTS):
        ch.shm.cmd.slot[i].seq = 1 << 40
    with pytest.raises(ChannelsCorrupt, match="command ring"):
        ch.send_command("start")
    before = ch.status()
    ch.shm.status.seq = 1  # a writer that never finishes
    t0 = time.monotonic()
    assert ch.status() == before  # not now: the last copy (tests/host/test_status_lock.py)
    assert time.monotonic() - t0 < 2.0


# ---- truncation ---------------------------------------------------------------------------------


def test_a_sealed_segment_cannot_be_resized_and_maps_as_a_channel() -> None:
    fd = segment.create_sealed("xrf-test-seal")
    try:
        assert segment.is_sealed(fd) and os.fstat(fd).st_size == SHM_SIZE
        for size in (0, 4096, SHM_SIZE * 2):
            with pytest.raises(PermissionError):
                os.ftruncate(fd, size)
        # Another open of the same memfd (as the loop would through /proc): still sealed.
        again = os.open(f"/proc/self/fd/{fd}", os.O_RDWR)
        try:
            with pytest.raises(PermissionError):
                os.ftruncate(again, 0)
        finally:
            os.close(again)
        with pytest.raises(ChannelsError, match="gave up"):
            Channels.open_fd(fd, "sealed", wait_s=0.05)  # nothing initialised it yet
        import mmap

        m = mmap.mmap(fd, SHM_SIZE)
        shm = ffi.from_buffer("struct xrf_shm *", m)
        lib.xrf_shm_init(shm)
        shm.info.cycle_freq = 1000
        shm.info.ros2xeno_schema = b"float64 a"
        shm.info.xeno2ros_schema = b"float64 b"
        lib.xrf_shm_publish_ready(shm)
        with Channels.open_fd(fd, "sealed", wait_s=1) as c:
            assert c.info["cycle_freq"] == 1000 and c.xeno2ros_codec.field_names == ["b"]
        del shm
        m.close()
    finally:
        os.close(fd)
