"""``Channels``: one loop's segment, mapped read-write, as the host uses it.

The face the CLI, the appliance and the ROS 2 bridge hold: opening and closing, the constant
part (``info``, the message codecs), the status and its histograms, commands, Ros2Xeno in,
telemetry and monitor readers, the doorbell, host supervision, and whether the loop behind the
name is still this one. Each of those is a thin method over the module of the package that
does the job (segment, status, commands, rings); this class only holds the mapping they share.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import time
from typing import Any

import numpy as np

from ..msgdef import Codec, MsgError
from . import commands, segment
from .binding import CData, c_str, ffi, lib
from .commands import CommandResult
from .errors import ChannelsCorrupt, ChannelsError, StatusBusy
from .names import HOST_LOST_ACTIONS
from .rings import MonitorReader, TelemetryReader
from .segment import Identity, shm_path
from .status import (
    Histogram,
    Status,
    StatusReader,
    histograms_of,
    state_key_of,
    status_from_struct,
    timing_words_of,
)


def _char_array_fields(ctype: CData) -> set[str]:
    return {name for name, f in ctype.fields if f.type.kind == "array" and f.type.item.cname == "char"}


# What the runtime writes into xrf_info (runtime.cpp, Runtime::enter): a value outside these is
# not a loop of ours speaking, and nothing downstream (the watcher's period and priority, the
# codecs) may take it.
_INFO_RANGES = {
    "cycle_freq": (1, 100_000),
    "priority": (0, 99),
    "cpu": (-1, 1 << 16),
    "rt_sched": (0, 1),
    "ros2xeno_size": (0, lib.XRF_MSG_MAX),
    "xeno2ros_size": (0, lib.XRF_MSG_MAX),
}


def take_info(name: str, shm: CData) -> dict[str, Any]:
    """The loop's info block, copied once into our memory and checked (ChannelsCorrupt): the
    loop writes it before `ready` and never again, so what it says later is not taken."""
    ctype = ffi.typeof("struct xrf_info")
    copy = ffi.new("struct xrf_info *")
    ffi.memmove(copy, ffi.addressof(shm, "info"), ffi.sizeof(ctype))
    strings = _char_array_fields(ctype)
    # c_str stops at the array's end: a name without its NUL is cut, never read beyond.
    info: dict[str, Any] = {
        f: c_str(getattr(copy, f)) if f in strings else int(getattr(copy, f)) for f, _ in ctype.fields
    }
    for field, (low, high) in _INFO_RANGES.items():
        if not low <= info[field] <= high:
            raise ChannelsCorrupt(f"{name}: info.{field} = {info[field]}, outside {low}..{high}")
    return info


def take_codec(name: str, info: dict[str, Any], which: str) -> Codec:
    """The codec of a message from the schema in the info copy: parsed by msgdef's bounded parser
    (at most XRF_MSG_MAX bytes of scalars and fixed arrays), else ChannelsCorrupt."""
    try:
        return Codec(info[f"{which}_schema"])
    except (MsgError, ValueError, OverflowError) as exc:
        raise ChannelsCorrupt(f"{name}: the {which} schema in the info block does not parse: {exc}") from None


class Channels:
    """One loop's shared memory, mapped read-write (commands and Ros2Xeno go host -> loop)."""

    def __init__(self, name: str, mapping: mmap.mmap, identity: Identity | None = None) -> None:
        """`mapping`: the whole segment, its loop ready. Takes what is constant for the run into
        our own memory now -- the fixed rings' geometry, the info block, the codecs -- checked
        (ChannelsCorrupt); nothing of it is read from the segment again."""
        self.name = name
        self._mmap = mapping
        # (st_dev, st_ino) of the object mapped: a loop that replaces it (same name, new object:
        # runtime.cpp unlinks and re-creates) or its removal is seen by comparing (replaced()).
        self.identity = identity
        self.shm = ffi.from_buffer("struct xrf_shm *", mapping)
        # The Ros2Xeno's sequence word, asked at every reader batch (30 a second with a dashboard
        # open): the two cffi lookups once, not per read (issue 30 item 4). Gone with close().
        self._ros2xeno_seq: CData | None = ffi.addressof(ffi.addressof(self.shm, "ros2xeno"), "seq")
        self._status = StatusReader(self.shm, name)
        try:
            self.geom: CData = segment.take_geometry(name, self.shm, len(mapping))
            self._info = take_info(name, self.shm)
            self._ros2xeno_codec = take_codec(name, self._info, "ros2xeno")
            self._xeno2ros_codec = take_codec(name, self._info, "xeno2ros")
        except ChannelsError:
            self.close()
            raise
        # A first copy now, so that a read that later finds the loop mid-write has one to give.
        with contextlib.suppress(StatusBusy):
            self._status.read()

    # -- opening ------------------------------------------------------------------------------

    @classmethod
    def open(cls, name: str = "xrf", wait_s: float = 5.0) -> Channels:
        """Map /dev/shm/<name>, wait up to wait_s for the loop to publish `ready`, check the layout."""
        mapping, identity = segment.attach(shm_path(name), wait_s)
        return cls(name, mapping, identity)

    @classmethod
    def open_fd(cls, fd: int, name: str, wait_s: float = 5.0) -> Channels:
        """Map the segment behind `fd` (a run's sealed memfd, which the appliance made: see
        segment_fd.py) and wait up to wait_s for its loop to publish `ready`. `name`: the run's
        segment name, for messages and replaced(). The descriptor stays the caller's."""
        mapping = segment.map_fd(fd, name)
        try:
            segment.wait_ready(name, mapping, wait_s)
        except BaseException:
            mapping.close()
            raise
        return cls(name, mapping, None)

    def close(self) -> None:
        """Unmap. Objects read from this Channels (readers, cdata) must not be used afterwards."""
        self.shm = self._ros2xeno_seq = None
        try:
            self._mmap.close()
        except BufferError:
            # Some cdata still points into the mapping; it is released with the last reference.
            pass

    def __enter__(self) -> Channels:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- constant part ------------------------------------------------------------------------

    @property
    def info(self) -> dict[str, Any]:
        """The info block as the loop published it before `ready` (copied at open)."""
        return self._info

    @property
    def ros2xeno_codec(self) -> Codec:
        return self._ros2xeno_codec

    @property
    def xeno2ros_codec(self) -> Codec:
        return self._xeno2ros_codec

    # -- status -------------------------------------------------------------------------------

    def status_copy(self) -> CData:
        """One consistent copy of the status block (a ``struct xrf_status *``), as status() reads
        it (the last good copy while the loop writes; StatusBusy, ChannelsCorrupt): for a caller
        that makes several things of one copy (the timing task once a second: the timing series'
        sample, the state refresh, the timing message; issue 30 item 4). Read it with
        status.status_from_struct, state_key_of, timing_words_of, histograms_of."""
        return self._status.read()

    def status(self) -> Status:
        """The status block as of the loop's last complete write; while the loop is in the middle
        of one, the last copy read (ask again for a newer). StatusBusy when none was read yet,
        ChannelsCorrupt when the block is kept locked on purpose (channels/status.py)."""
        return status_from_struct(self.status_copy())

    def fresh_status(self) -> Status | None:
        """The status as of now, or None while the loop is in the middle of writing it (ask
        again): for a caller that acts on where the loop is, where an older copy would mislead."""
        s = self._status.read_fresh()
        return None if s is None else status_from_struct(s)

    def state_key(self) -> tuple[int, int, bool, int]:
        """(state, cmd_rejected, running, last_error) from one consistent copy of the status
        block, without converting the rest of it (status() converts ~25 fields through cffi: the
        reader checks this after every batch, 50 times a second with a dashboard open)."""
        return state_key_of(self.status_copy())

    def histograms(self) -> dict[str, Histogram]:
        return histograms_of(self.status_copy())

    def timing_words(self) -> tuple[dict[str, int], np.ndarray]:
        """status.timing_words_of a fresh consistent copy of the status block."""
        return timing_words_of(self.status_copy())

    @property
    def status_copies(self) -> int:
        """Consistent copies of the status block made so far (tests: how often a user copies it)."""
        return self._status.copies

    # -- commands -----------------------------------------------------------------------------

    def send_command(self, cmd: str | int, source: int = lib.XRF_SOURCE_CLI) -> int:
        """Queue a command; returns its ticket. Invalid numbers are queued too: the loop rejects
        them with a reason, which is what a user asking for them should see."""
        return commands.send(self.shm, self.name, cmd, source)

    def wait_command(self, ticket: int, timeout: float = 2.0) -> CommandResult:
        return commands.wait(self._status.read, self.name, ticket, timeout)

    # -- data in ------------------------------------------------------------------------------

    def write_ros2xeno(self, values: dict[str, Any]) -> bytes:
        """Encode `values` (missing fields are 0) and publish them; returns the bytes written."""
        payload = self.ros2xeno_codec.encode(values)
        rc = lib.xrf_data_in_write(ffi.addressof(self.shm, "ros2xeno"), payload, len(payload), time.monotonic_ns())
        if rc != 0:
            raise ChannelsError(f"{self.name}: writing Ros2Xeno failed: {os.strerror(-rc)}")
        return payload

    @property
    def ros2xeno_seq(self) -> int:
        """The Ros2Xeno's write sequence (it moves with every write, odd while one is under way):
        a reader that saw the same number has the same message already."""
        if self._ros2xeno_seq is None:
            raise ChannelsError(f"{self.name}: closed")
        return int(lib.xrfpy_load_u32(self._ros2xeno_seq))

    def read_ros2xeno(self) -> dict[str, Any] | None:
        """The Ros2Xeno the loop takes at its next cycle: the latest complete write by anyone
        (the appliance, the ROS 2 bridge, a CLI), decoded; all zero before the first write (the
        loop's own starts at zero); None while a writer is in the middle of one (ask again)."""
        codec = self.ros2xeno_codec
        data_in = ffi.addressof(self.shm, "ros2xeno")
        if lib.xrfpy_load_u32(ffi.addressof(data_in, "seq")) == 0:
            return codec.decode(bytes(codec.size))
        out = ffi.new("uint8_t[]", max(codec.size, 1))
        last_seq = ffi.new("uint32_t *", 0)  # "newer than nothing": any complete message
        if lib.xrf_data_in_try_read(data_in, last_seq, out, codec.size, ffi.NULL) != 1:
            return None
        return codec.decode(bytes(ffi.buffer(out, codec.size)))

    # -- data out -----------------------------------------------------------------------------

    def telemetry_reader(self, from_start: bool = False) -> TelemetryReader:
        return TelemetryReader(self, from_start)

    def monitor_reader(self, from_start: bool = False) -> MonitorReader:
        return MonitorReader(self, from_start)

    @property
    def doorbell(self) -> int:
        return int(lib.xrfpy_load_u32(ffi.addressof(self.shm, "doorbell")))

    def wait_doorbell(self, seen: int, timeout_ms: int) -> int:
        """Block (GIL released) until the doorbell differs from `seen` or timeout_ms passes."""
        return int(lib.xrf_doorbell_wait(self.shm, seen, timeout_ms))

    # -- simulated time (XRF_VIRTUAL_TIME, docs/rt_core/runtime.md "Simulated time") -----------

    @property
    def virtual_time(self) -> bool:
        """The loop runs in simulated time (its clock skips idle time; it may be held)."""
        return bool(lib.xrfpy_load_u32(ffi.addressof(self.shm.vtime, "active")))

    def run_until(self, cycles: int | None) -> None:
        """Simulated time: let the loop run until status.cycles reaches `cycles`, then hold it
        there; None lets it run free. A host feeding inputs at exact loop times writes them while
        the loop is held, then raises the limit."""
        value = -1 if cycles is None else int(cycles)  # -1: all ones, the loop's UINT64_MAX
        lib.xrfpy_store_i64(ffi.cast("int64_t *", ffi.addressof(self.shm.vtime, "run_until")), value)

    # -- supervision --------------------------------------------------------------------------

    def host_heartbeat(self) -> None:
        lib.xrfpy_store_i64(ffi.addressof(self.shm, "host_heartbeat_ns"), time.monotonic_ns())

    def configure_host_timeout(self, timeout_ms: int, action: str | int = "pause") -> None:
        """Ask the loop to pause/stop when no heartbeat came for timeout_ms (0 turns it off)."""
        code = HOST_LOST_ACTIONS[action] if isinstance(action, str) else int(action)
        self.host_heartbeat()  # a fresh heartbeat first, so enabling supervision trips nothing
        lib.xrfpy_store_u32(ffi.addressof(self.shm, "host_timeout_action"), code)
        lib.xrfpy_store_u32(ffi.addressof(self.shm, "host_timeout_ms"), timeout_ms)

    def force_sim_outputs_off(self) -> None:
        """The simulated counterpart of an FPGA RESET after the loop died: the plant ignores PWM."""
        lib.xrfpy_store_u32(ffi.addressof(self.shm.sim, "forced_off"), 1)

    # -- which loop -----------------------------------------------------------------------------

    def replaced(self) -> bool:
        """True when /dev/shm/<name> is no longer the object mapped here: removed (its run ended
        and its owner cleaned up), or re-created by a new loop of the same name. What this
        object shows is then a past run's; Channels.open(name) reaches the current one."""
        return self.identity is not None and segment.identity(shm_path(self.name)) != self.identity

    def loop_alive(self) -> bool:
        """The loop process behind this object still runs loop() (a loop that returned, crashed
        or was killed is not)."""
        if not self.status().running:
            return False
        pid = self.info["pid"]
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # another user's loop (the appliance's run user): it exists
            pass
        return True
