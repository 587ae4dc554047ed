"""Playing the loop's part from Python, so the rings, the command path and the CLI can be tested
without a loop process.

``create_for_test`` makes a segment as a loop's start does (``xrf_shm_init``, info, ready);
``LoopSide`` then does what a cycle does with it — takes commands through the one command table
in C, publishes telemetry and monitor lines, rings the doorbell — with channels.c's own functions.
Tests only: never alongside a real loop on the same segment. It lives with the tests, not in
``xrflab.channels``: the appliance never plays the loop, and ``Channels`` needs nothing from here
(tests/lint/layers.py keeps the package free of the cycle it once made).
"""

from __future__ import annotations

import mmap
import os
import time
from collections.abc import Callable
from typing import Any

from xrflab.channels import SHM_SIZE, STAGE_NAMES, Channels, ffi, lib, shm_path
from xrflab.channels.binding import CData
from xrflab.msgdef import Codec


def create_for_test(
    name: str,
    *,
    ros2xeno_schema: str = "float64 steer_left\nfloat64 steer_right",
    xeno2ros_schema: str = "float64 pos_left\nfloat64 pos_right",
    cycle_freq: int = 1000,
    program: str = "python-test",
    channels: int | None = None,
) -> Channels:
    """Create /dev/shm/<name> as a loop would (xrf_shm_init, info, ready) and open it.

    For tests only: there is no loop behind it; drive it with ``LoopSide(channels)``. The caller
    unlinks the object (``shm_path(name).unlink()``) when done.
    """
    path = shm_path(name)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o660)
    try:
        os.ftruncate(fd, SHM_SIZE)
        mapping = mmap.mmap(fd, SHM_SIZE, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        st = os.fstat(fd)
    finally:
        os.close(fd)
    shm = ffi.from_buffer("struct xrf_shm *", mapping)
    lib.xrf_shm_init(shm)
    if channels is not None:  # the bench's count, as the host writes it (any value: hostile tests)
        shm.channels = channels
    info = shm.info
    info.pid = os.getpid()
    info.cycle_freq = cycle_freq
    info.write_decimator_freq = cycle_freq
    info.monitor_freq = 0
    info.ros2xeno_size = Codec(ros2xeno_schema).size
    info.xeno2ros_size = Codec(xeno2ros_schema).size
    info.cpu = -1
    for attr, text in (
        ("backend", "posix"),
        ("transport", "sim"),
        ("sim", "relbot"),
        ("program", program),
        ("ros2xeno_schema", ros2xeno_schema),
        ("xeno2ros_schema", xeno2ros_schema),
    ):
        raw = text.encode()
        if len(raw) >= len(getattr(info, attr)):
            raise ValueError(f"{attr} too long for the shared memory")
        setattr(info, attr, raw)
    # As a loop in loop(): running before ready (set_state(..., running=False) plays its end).
    status = ffi.addressof(shm, "status")
    lib.xrf_status_write_begin(status)
    status.running = 1
    lib.xrf_status_write_end(status)
    lib.xrf_shm_publish_ready(shm)
    del shm, status
    return Channels(name, mapping, (st.st_dev, st.st_ino))


class LoopSide:
    """The loop's half of the channels, driven from Python (tests only; never alongside a loop)."""

    def __init__(self, channels: Channels) -> None:
        self._ch = channels
        self._shm = channels.shm
        self._ros2xeno_seq = ffi.new("uint32_t *", 0)
        self._ros2xeno_buf = ffi.new("uint8_t[]", lib.XRF_MSG_MAX)

    def _write_status(self, update: Callable[[CData], None]) -> None:
        status = ffi.addressof(self._shm, "status")
        lib.xrf_status_write_begin(status)
        update(status)
        lib.xrf_status_write_end(status)

    def ring_doorbell(self) -> None:
        if lib.xrf_doorbell_should_ring(self._shm):
            lib.xrf_doorbell_wake(self._shm)

    def set_state(self, state: int, running: bool = True) -> None:
        def update(s: CData) -> None:
            s.state = state
            s.running = int(running)

        self._write_status(update)

    def poll_command(self) -> tuple[int, int, int] | None:
        """Take one queued command: (ticket, cmd, source), or None when there is none."""
        slot = ffi.new("struct xrf_cmd_slot *")
        if not lib.xrf_cmd_poll(ffi.addressof(self._shm, "cmd"), slot):
            return None
        return int(slot.ticket), int(slot.cmd), int(slot.source)

    def handle_commands(self) -> int:
        """Apply queued commands with the C command table as the loop does; returns how many."""
        handled = 0
        while (taken := self.poll_command()) is not None:
            ticket, cmd, _source = taken
            self._apply(ticket, cmd)
            handled += 1
        if handled:
            self.ring_doorbell()
        return handled

    def _apply(self, ticket: int, cmd: int) -> None:
        current = self._shm.status.state
        target = lib.xrf_cmd_transition(current, cmd)

        def update(s: CData) -> None:
            s.cmd_done = ticket
            slot = ticket % lib.XRF_CMD_RESULTS
            s.cmd_results[slot] = (ticket << 1) | (0 if target > 0 else 1)
            if target > 0:
                s.state = target
                s.last_cmd = cmd
                return
            reason = ffi.new("char[]", lib.XRF_REASON_MAX)
            lib.xrf_cmd_reject_reason(current, cmd, reason, lib.XRF_REASON_MAX)
            ffi.memmove(s.cmd_reasons[slot], reason, lib.XRF_REASON_MAX)
            s.cmd_rejected = ticket
            s.last_rejected_cmd = cmd
            s.reject_code = -target
            s.rejected_count += 1
            ffi.memmove(s.reject_reason, reason, lib.XRF_REASON_MAX)

        self._write_status(update)

    def count_cycle(self, n: int = 1) -> None:
        def update(s: CData) -> None:
            s.cycles += n
            s.heartbeat_ns = time.monotonic_ns()

        self._write_status(update)

    def add_timing(self, stage: str, ns: int) -> None:
        index = STAGE_NAMES.index(stage)
        self._write_status(lambda s: lib.xrf_hist_add(ffi.addressof(s.hist, index), ns))

    def read_ros2xeno(self) -> dict[str, Any] | None:
        """The newest complete Ros2Xeno since the last call, decoded, or None."""
        codec = self._ch.ros2xeno_codec
        t_sent = ffi.new("int64_t *")
        if not lib.xrf_data_in_try_read(
            ffi.addressof(self._shm, "ros2xeno"), self._ros2xeno_seq, self._ros2xeno_buf, codec.size, t_sent
        ):
            return None
        return codec.decode(bytes(ffi.buffer(self._ros2xeno_buf, codec.size)))

    def publish_telemetry(
        self,
        cycle: int,
        *,
        t_ns: int | None = None,
        state: int | None = None,
        enc: list[int] | None = None,
        din: list[int] | None = None,
        pwm: list[int] | None = None,
        dout: list[int] | None = None,
        xeno2ros: dict[str, Any] | bytes | None = None,
        ros2xeno_t_sent_ns: int = 0,
        ring: bool = True,
    ) -> None:
        payload = xeno2ros if isinstance(xeno2ros, bytes) else self._ch.xeno2ros_codec.encode(xeno2ros or {})
        slot = ffi.cast(
            "struct xrf_telemetry *", lib.xrf_bcast_begin(ffi.addressof(self._shm, "telem_ring"), self._shm.telem)
        )
        slot.hdr.cycle = cycle
        slot.hdr.t_ns = time.monotonic_ns() if t_ns is None else t_ns
        slot.state = self._shm.status.state if state is None else state
        # Whole arrays (a reused slot keeps the old values of channels not given).
        n = lib.XRF_MAX_CHANNELS
        slot.enc = (enc or []) + [0] * (n - len(enc or []))
        slot.din = (din or []) + [0] * (2 * n - len(din or []))
        slot.pwm = (pwm or []) + [0] * (n - len(pwm or []))
        slot.dout = (dout or []) + [0] * (n - len(dout or []))
        slot.size = len(payload)
        slot.ros2xeno_t_sent_ns = ros2xeno_t_sent_ns
        ffi.memmove(slot.data, payload, len(payload))
        lib.xrf_bcast_commit(ffi.addressof(self._shm, "telem_ring"), slot)
        if ring:
            self.ring_doorbell()

    def publish_monitor(self, cycle: int, text: str, *, t_ns: int | None = None, ring: bool = True) -> None:
        raw = text.encode()[: lib.XRF_MONITOR_TEXT]
        slot = ffi.cast(
            "struct xrf_monitor_line *",
            lib.xrf_bcast_begin(ffi.addressof(self._shm, "monitor_ring"), self._shm.monitor),
        )
        slot.hdr.cycle = cycle
        slot.hdr.t_ns = time.monotonic_ns() if t_ns is None else t_ns
        slot.len = len(raw)
        ffi.memmove(slot.text, raw, len(raw))
        lib.xrf_bcast_commit(ffi.addressof(self._shm, "monitor_ring"), slot)
        if ring:
            self.ring_doorbell()
