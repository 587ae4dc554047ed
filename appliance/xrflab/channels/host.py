"""Host side of a loop process's shared memory (``/dev/shm/<name>``), through cffi.

The layout and every ring operation come from rt_core's channels.h/channels.c (see
``_cffi_build``); this module only adds Python types around them. One ``Channels`` object maps one
run's shared memory. Readers of the broadcast rings (telemetry, monitor) keep their own cursor,
so any number of hosts can watch the same loop without disturbing it or each other.

``create_for_test`` and ``LoopSide`` play the loop's part from Python so the rings, the command
path and the CLI can be tested without a loop process.
"""

from __future__ import annotations

import errno
import mmap
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import _cffi_build
from .msgdef import Codec

_binding = _cffi_build.load()
ffi = _binding.ffi
lib = _binding.lib

SHM_DIR = Path("/dev/shm")
SHM_SIZE: int = ffi.sizeof("struct xrf_shm")

# Stage names in the order of the XRF_STAGE_* indices; the numbers themselves come from the header.
STAGE_NAMES: tuple[str, ...] = tuple(
    sorted(
        ("wakeup", "fpga", "data", "cmd", "monitor", "hook", "logger", "cycle"),
        key=lambda name: getattr(lib, "XRF_STAGE_" + name.upper()),
    )
)

HOST_LOST_ACTIONS = {
    "ignore": lib.XRF_HOST_LOST_IGNORE,
    "pause": lib.XRF_HOST_LOST_PAUSE,
    "stop": lib.XRF_HOST_LOST_STOP,
}

_STATUS_READ_ATTEMPTS = 100


class ChannelsError(RuntimeError):
    """The shared memory is missing, foreign, or a channel refused an operation."""


class CommandRingFull(ChannelsError):
    """The loop is not taking commands (stopped cycling, or far behind)."""


class CommandTimeout(ChannelsError, TimeoutError):
    """A command was queued but the loop did not handle it in time."""


# ---- names from the C side ----------------------------------------------------------------------


def _c_str(ptr: Any) -> str:
    return ffi.string(ptr).decode("utf-8", "replace")


def state_name(state: int) -> str:
    return _c_str(lib.xrf_state_name(state))


def command_name(cmd: int) -> str:
    return _c_str(lib.xrf_cmd_name(cmd))


COMMAND_NUMBERS: dict[str, int] = {command_name(c): c for c in range(lib.XRF_CMD_INITIALISE, lib.XRF_CMD_QUIT + 1)}
STATE_NUMBERS: dict[str, int] = {state_name(s): s for s in range(lib.XRF_STATE_IDLE, lib.XRF_STATE_QUIT + 1)}


def command_number(cmd: str | int) -> int:
    """A command name ("start") or number; numbers pass unchecked (the loop rejects bad ones)."""
    if isinstance(cmd, int):
        return cmd
    text = cmd.strip().lower()
    if text.lstrip("-").isdigit():
        return int(text)
    if text not in COMMAND_NUMBERS:
        raise ValueError(f"unknown command {cmd!r}; commands: {', '.join(COMMAND_NUMBERS)}")
    return COMMAND_NUMBERS[text]


def allowed_commands(state: int) -> list[str]:
    """Names of the commands the loop accepts in `state`, from the one command table in C."""
    return [name for name, number in COMMAND_NUMBERS.items() if lib.xrf_cmd_transition(state, number) > 0]


def _char_array_fields(ctype: Any) -> set[str]:
    return {name for name, f in ctype.fields if f.type.kind == "array" and f.type.item.cname == "char"}


# ---- snapshots ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Status:
    state: int
    state_name: str
    last_error: int
    last_cmd: int
    last_rejected_cmd: int
    reject_code: int
    reject_reason: str
    rejected_count: int
    running: bool
    end_reason: int  # XRF_END_*: why loop() returned (0 while it runs, or if it never did)
    cmd_done: int
    cmd_rejected: int
    cycles: int
    missed: int
    t_start_ns: int
    heartbeat_ns: int
    idle_ns: int
    demotions: int
    log_written: int
    log_lost: int
    telem_published: int
    monitor_dropped: int
    host_lost: int
    doorbell_dropped: int  # doorbell rings the backend refused (EVL: proxy ring full)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class CommandResult:
    ticket: int
    accepted: bool
    state: int
    state_name: str
    reason: str


@dataclass(frozen=True)
class Telemetry:
    cycle: int
    t_ns: int
    state: int
    enc: list[int]
    din: list[int]
    pwm: list[int]
    dout: list[int]
    xeno2ros: dict[str, Any]
    ros2xeno_t_sent_ns: int

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class MonitorLine:
    cycle: int
    t_ns: int
    text: str


@dataclass(frozen=True)
class Histogram:
    """One stage's timing histogram; `edges` are the lower edges (ns) of the non-empty buckets."""

    count: int
    min: int
    max: int
    mean: float
    edges: list[int] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)

    def percentile(self, p: float) -> int:
        """Lower edge (ns) of the bucket holding the p-th percentile, clamped to [min, max]."""
        if not 0 <= p <= 100:
            raise ValueError("percentile must be within 0..100")
        if self.count == 0:
            return 0
        rank = p / 100.0 * self.count
        seen = 0
        for edge, n in zip(self.edges, self.counts):
            seen += n
            if seen >= rank and seen > 0:
                return min(max(edge, self.min), self.max)
        return self.max


def _status_from_struct(s: Any) -> Status:
    return Status(
        state=s.state,
        state_name=state_name(s.state),
        last_error=s.last_error,
        last_cmd=s.last_cmd,
        last_rejected_cmd=s.last_rejected_cmd,
        reject_code=s.reject_code,
        reject_reason=_c_str(s.reject_reason),
        rejected_count=s.rejected_count,
        running=bool(s.running),
        end_reason=s.end_reason,
        cmd_done=s.cmd_done,
        cmd_rejected=s.cmd_rejected,
        cycles=s.cycles,
        missed=s.missed,
        t_start_ns=s.t_start_ns,
        heartbeat_ns=s.heartbeat_ns,
        idle_ns=s.idle_ns,
        demotions=s.demotions,
        log_written=s.log_written,
        log_lost=s.log_lost,
        telem_published=s.telem_published,
        monitor_dropped=s.monitor_dropped,
        host_lost=s.host_lost,
        doorbell_dropped=s.doorbell_dropped,
    )


def _histogram_from_struct(h: Any) -> Histogram:
    edges: list[int] = []
    counts: list[int] = []
    for bucket in range(lib.XRF_HIST_BUCKETS):
        n = h.buckets[bucket]
        if n:
            edges.append(lib.xrf_hist_bucket_low(bucket))
            counts.append(n)
    count = h.count
    return Histogram(
        count=count,
        min=h.min_ns if count else 0,
        max=h.max_ns,
        mean=h.sum_ns / count if count else 0.0,
        edges=edges,
        counts=counts,
    )


# ---- broadcast ring readers ---------------------------------------------------------------------


class _BroadcastReader:
    """A private cursor over one broadcast ring; counts what the loop overwrote before we read."""

    def __init__(self, ring: Any, slots: Any, slot_type: str, from_start: bool) -> None:
        self._ring = ring
        self._slots = slots
        head = lib.xrfpy_load_u64(ffi.addressof(ring, "head"))
        self._cursor = ffi.new("uint64_t *", 0 if from_start else head)
        self._lost = ffi.new("uint64_t *", 0)
        self._out = ffi.new(slot_type + " *")

    @property
    def lost(self) -> int:
        return int(self._lost[0])

    @property
    def cursor(self) -> int:
        return int(self._cursor[0])

    def _read_raw(self, max_items: int | None) -> list[Any]:
        items = []
        while max_items is None or len(items) < max_items:
            if not lib.xrf_bcast_read(self._ring, self._slots, self._cursor, self._out, self._lost):
                break
            items.append(self._convert(self._out))
        return items

    def _convert(self, slot: Any) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError


class TelemetryReader(_BroadcastReader):
    def __init__(self, channels: Channels, from_start: bool = False) -> None:
        shm = channels.shm
        super().__init__(ffi.addressof(shm, "telem_ring"), shm.telem, "struct xrf_telemetry", from_start)
        self._codec = channels.xeno2ros_codec

    def read(self, max_items: int | None = None) -> list[Telemetry]:
        return self._read_raw(max_items)

    def _convert(self, t: Any) -> Telemetry:
        payload = bytes(ffi.buffer(t.data, min(t.size, lib.XRF_MSG_MAX)))
        return Telemetry(
            cycle=t.hdr.cycle,
            t_ns=t.hdr.t_ns,
            state=t.state,
            enc=list(t.enc),
            din=list(t.din),
            pwm=list(t.pwm),
            dout=list(t.dout),
            xeno2ros=self._codec.decode(payload) if len(payload) >= self._codec.size else {},
            ros2xeno_t_sent_ns=t.ros2xeno_t_sent_ns,
        )


class MonitorReader(_BroadcastReader):
    def __init__(self, channels: Channels, from_start: bool = False) -> None:
        shm = channels.shm
        super().__init__(ffi.addressof(shm, "monitor_ring"), shm.monitor, "struct xrf_monitor_line", from_start)

    def read(self, max_items: int | None = None) -> list[MonitorLine]:
        return self._read_raw(max_items)

    def _convert(self, m: Any) -> MonitorLine:
        n = min(m.len, lib.XRF_MONITOR_TEXT)
        text = bytes(ffi.buffer(m.text, n)).decode("utf-8", "replace")
        return MonitorLine(cycle=m.hdr.cycle, t_ns=m.hdr.t_ns, text=text)


# ---- the shared memory --------------------------------------------------------------------------


def shm_path(name: str) -> Path:
    """/dev/shm/<name>. A run started by the appliance has ``<run folder>/<name>``: its loop sees
    that folder of the host's /dev/shm as its own /dev/shm (xrflab.guest)."""
    parts = name.split("/") if name else []
    if not 1 <= len(parts) <= 2 or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"bad shared-memory name {name!r} (a plain name, or folder/name)")
    return SHM_DIR.joinpath(*parts)


class Channels:
    """One loop's shared memory, mapped read-write (commands and Ros2Xeno go host -> loop)."""

    def __init__(self, name: str, mapping: mmap.mmap, identity: tuple[int, int] | None = None) -> None:
        self.name = name
        self._mmap = mapping
        # (st_dev, st_ino) of the object mapped: a loop that replaces it (same name, new object:
        # runtime.cpp unlinks and re-creates) or its removal is seen by comparing (replaced()).
        self.identity = identity
        self.shm = ffi.from_buffer("struct xrf_shm *", mapping)
        self._info: dict[str, Any] | None = None
        self._ros2xeno_codec: Codec | None = None
        self._xeno2ros_codec: Codec | None = None

    # -- opening ------------------------------------------------------------------------------

    @classmethod
    def open(cls, name: str = "xrf", wait_s: float = 5.0) -> Channels:
        """Map /dev/shm/<name>, wait up to wait_s for the loop to publish `ready`, check the layout."""
        path = shm_path(name)
        deadline = time.monotonic() + wait_s
        waiting_for = "the shared memory object to appear"
        while True:
            mapping, identity = _try_map(path)
            if mapping is not None:
                shm = ffi.from_buffer("struct xrf_shm *", mapping)
                magic = lib.xrfpy_load_u32(ffi.addressof(shm, "magic"))
                if magic == 0:
                    waiting_for = "the loop to initialise it"
                else:
                    _check_layout(path, shm)
                    if lib.xrfpy_load_u32(ffi.addressof(shm, "ready")):
                        return cls(name, mapping, identity)
                    waiting_for = "the loop to mark it ready"
                del shm
                mapping.close()
            if time.monotonic() >= deadline:
                raise ChannelsError(f"{path}: gave up after {wait_s:g} s waiting for {waiting_for}")
            time.sleep(0.01)

    def close(self) -> None:
        """Unmap. Objects read from this Channels (readers, cdata) must not be used afterwards."""
        self.shm = None
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
        if self._info is None:
            info = self.shm.info
            strings = _char_array_fields(ffi.typeof("struct xrf_info"))
            self._info = {
                name: _c_str(getattr(info, name)) if name in strings else int(getattr(info, name))
                for name, _ in ffi.typeof("struct xrf_info").fields
            }
        return self._info

    @property
    def ros2xeno_codec(self) -> Codec:
        if self._ros2xeno_codec is None:
            self._ros2xeno_codec = Codec(self.info["ros2xeno_schema"])
        return self._ros2xeno_codec

    @property
    def xeno2ros_codec(self) -> Codec:
        if self._xeno2ros_codec is None:
            self._xeno2ros_codec = Codec(self.info["xeno2ros_schema"])
        return self._xeno2ros_codec

    # -- status -------------------------------------------------------------------------------

    def _status_struct(self) -> Any:
        out = ffi.new("struct xrf_status *")
        for _ in range(_STATUS_READ_ATTEMPTS):
            if lib.xrf_status_read(ffi.addressof(self.shm, "status"), out) == 0:
                return out
            time.sleep(0)
        raise ChannelsError(f"{self.name}: status block stays locked (loop died while writing it?)")

    def status(self) -> Status:
        return _status_from_struct(self._status_struct())

    def histograms(self) -> dict[str, Histogram]:
        s = self._status_struct()
        return {name: _histogram_from_struct(s.hist[i]) for i, name in enumerate(STAGE_NAMES)}

    # -- commands -----------------------------------------------------------------------------

    def send_command(self, cmd: str | int, source: int = lib.XRF_SOURCE_CLI) -> int:
        """Queue a command; returns its ticket. Invalid numbers are queued too: the loop rejects
        them with a reason, which is what a user asking for them should see."""
        number = command_number(cmd)
        ticket = lib.xrf_cmd_send(ffi.addressof(self.shm, "cmd"), number, source, time.monotonic_ns())
        if ticket == -errno.EAGAIN:
            raise CommandRingFull(
                f"{self.name}: command ring full ({lib.XRF_CMD_SLOTS} pending): "
                "the loop is not taking commands (is it still running?)"
            )
        if ticket <= 0:
            raise ChannelsError(f"{self.name}: xrf_cmd_send failed ({ticket})")
        return int(ticket)

    def wait_command(self, ticket: int, timeout: float = 2.0) -> CommandResult:
        deadline = time.monotonic() + timeout
        slot = ticket % lib.XRF_CMD_RESULTS
        while True:
            s = self._status_struct()
            if s.cmd_done >= ticket:
                result = int(s.cmd_results[slot])
                if result >> 1 == ticket:
                    accepted = not (result & 1)
                    reason = "" if accepted else _c_str(s.cmd_reasons[slot])
                else:
                    # More than XRF_CMD_RESULTS commands were handled since: the outcome is gone.
                    accepted, reason = False, "outcome no longer known (too many commands since)"
                return CommandResult(
                    ticket=ticket,
                    accepted=accepted,
                    state=int(s.state),
                    state_name=state_name(int(s.state)),
                    reason=reason,
                )
            if time.monotonic() >= deadline:
                st = _status_from_struct(s)
                raise CommandTimeout(
                    f"{self.name}: command #{ticket} not handled within {timeout:g} s "
                    f"(state {st.state_name}, loop {'running' if st.running else 'not running'})"
                )
            time.sleep(0.001)

    # -- data in ------------------------------------------------------------------------------

    def write_ros2xeno(self, values: dict[str, Any]) -> bytes:
        """Encode `values` (missing fields are 0) and publish them; returns the bytes written."""
        payload = self.ros2xeno_codec.encode(values)
        rc = lib.xrf_data_in_write(ffi.addressof(self.shm, "ros2xeno"), payload, len(payload), time.monotonic_ns())
        if rc != 0:
            raise ChannelsError(f"{self.name}: writing Ros2Xeno failed: {os.strerror(-rc)}")
        return payload

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

    def loop_side(self) -> LoopSide:
        return LoopSide(self)

    # -- which loop -----------------------------------------------------------------------------

    def replaced(self) -> bool:
        """True when /dev/shm/<name> is no longer the object mapped here: removed (its run ended
        and its owner cleaned up), or re-created by a new loop of the same name. What this
        object shows is then a past run's; Channels.open(name) reaches the current one."""
        return self.identity is not None and _identity(shm_path(self.name)) != self.identity

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


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _try_map(path: Path) -> tuple[mmap.mmap | None, tuple[int, int] | None]:
    try:
        fd = os.open(path, os.O_RDWR)
    except FileNotFoundError:
        return None, None
    try:
        st = os.fstat(fd)
        size = st.st_size
        if 0 < size < SHM_SIZE:
            # Not a loop still sizing it (ftruncate is immediate): a loop built against another
            # layout. Say so instead of waiting for an object that will never fit.
            raise ChannelsError(
                f"{path}: {size} bytes, this host expects {SHM_SIZE}: the controller was built "
                "against another rt_core; rebuild it"
            )
        if size < SHM_SIZE:
            return None, None
        return mmap.mmap(fd, SHM_SIZE, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE), (st.st_dev, st.st_ino)
    finally:
        os.close(fd)


def remove_if_owned(name: str, pid: int) -> bool:
    """Unlink /dev/shm/<name> if it is the segment of loop process `pid` (`xrf run` after its
    controller exited: nothing needs the final state any more, the summary is printed; readers
    still attached keep their mapping). A segment a newer loop made under the name is left."""
    path = shm_path(name)
    mapping, identity = _try_map(path)
    if mapping is None:
        return False
    try:
        shm = ffi.from_buffer("struct xrf_shm *", mapping)
        owned = shm.magic == lib.XRF_SHM_MAGIC and shm.info.pid == pid
        del shm
    finally:
        mapping.close()
    if owned and _identity(path) == identity:
        try:
            path.unlink()
        except FileNotFoundError:
            return False
        return True
    return False


def _check_layout(path: Path, shm: Any) -> None:
    if shm.magic != lib.XRF_SHM_MAGIC:
        raise ChannelsError(f"{path}: not an XRF shared-memory object (magic {shm.magic:#x})")
    if shm.version != lib.XRF_SHM_VERSION:
        raise ChannelsError(
            f"{path}: layout version {shm.version}, this host speaks {lib.XRF_SHM_VERSION} "
            "(rebuild the controller against this rt_core)"
        )
    if shm.size != SHM_SIZE:
        raise ChannelsError(f"{path}: layout size {shm.size} bytes, expected {SHM_SIZE}")


# ---- the loop's part, for tests -----------------------------------------------------------------


def create_for_test(
    name: str,
    *,
    ros2xeno_schema: str = "float64 steer_left\nfloat64 steer_right",
    xeno2ros_schema: str = "float64 pos_left\nfloat64 pos_right",
    cycle_freq: int = 1000,
    program: str = "python-test",
) -> Channels:
    """Create /dev/shm/<name> as a loop would (xrf_shm_init, info, ready) and open it.

    For tests only: there is no loop behind it; drive it with ``channels.loop_side()``. The caller
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

    def _write_status(self, update: Any) -> None:
        status = ffi.addressof(self._shm, "status")
        lib.xrf_status_write_begin(status)
        update(status)
        lib.xrf_status_write_end(status)

    def ring_doorbell(self) -> None:
        if lib.xrf_doorbell_should_ring(self._shm):
            lib.xrf_doorbell_wake(self._shm)

    def set_state(self, state: int, running: bool = True) -> None:
        def update(s: Any) -> None:
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

        def update(s: Any) -> None:
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
        def update(s: Any) -> None:
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
        slot.enc = enc or [0] * 4
        slot.din = din or [0] * 8
        slot.pwm = pwm or [0] * 4
        slot.dout = dout or [0] * 4
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
