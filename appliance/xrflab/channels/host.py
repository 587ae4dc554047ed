"""``Channels``: one loop's segment, mapped read-write, as the host uses it.

The face the CLI, the appliance and the ROS 2 bridge hold: opening and closing, the constant
part (``info``, the message codecs), the status and its histograms, commands, Ros2Xeno in,
telemetry and monitor readers, the doorbell, host supervision, and whether the loop behind the
name is still this one. Each of those is a thin method over the module of the package that
does the job (segment, status, commands, rings); this class only holds the mapping they share.
"""

from __future__ import annotations

import mmap
import os
import time
from typing import TYPE_CHECKING, Any

from ..msgdef import Codec
from . import commands, segment
from .binding import CData, c_str, ffi, lib
from .commands import CommandResult
from .errors import ChannelsError
from .names import HOST_LOST_ACTIONS, STAGE_NAMES
from .rings import MonitorReader, TelemetryReader
from .segment import Identity, shm_path
from .status import Histogram, Status, histogram_from_struct, read_status, status_from_struct

if TYPE_CHECKING:
    from .testloop import LoopSide


def _char_array_fields(ctype: CData) -> set[str]:
    return {name for name, f in ctype.fields if f.type.kind == "array" and f.type.item.cname == "char"}


class Channels:
    """One loop's shared memory, mapped read-write (commands and Ros2Xeno go host -> loop)."""

    def __init__(self, name: str, mapping: mmap.mmap, identity: Identity | None = None) -> None:
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
        mapping, identity = segment.attach(shm_path(name), wait_s)
        return cls(name, mapping, identity)

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
                name: c_str(getattr(info, name)) if name in strings else int(getattr(info, name))
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

    def _status_struct(self) -> CData:
        return read_status(self.shm, self.name)

    def status(self) -> Status:
        return status_from_struct(self._status_struct())

    def histograms(self) -> dict[str, Histogram]:
        s = self._status_struct()
        return {name: histogram_from_struct(s.hist[i]) for i, name in enumerate(STAGE_NAMES)}

    # -- commands -----------------------------------------------------------------------------

    def send_command(self, cmd: str | int, source: int = lib.XRF_SOURCE_CLI) -> int:
        """Queue a command; returns its ticket. Invalid numbers are queued too: the loop rejects
        them with a reason, which is what a user asking for them should see."""
        return commands.send(self.shm, self.name, cmd, source)

    def wait_command(self, ticket: int, timeout: float = 2.0) -> CommandResult:
        return commands.wait(self.shm, self.name, ticket, timeout)

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
        """The loop's half of these channels, driven from Python (tests only)."""
        from .testloop import LoopSide  # only tests play the loop

        return LoopSide(self)

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
