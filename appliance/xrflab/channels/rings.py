"""Readers of the loop's broadcast rings: telemetry (one sample a cycle) and monitor lines.

The loop overwrites its rings without waiting for anyone (``xrf_bcast_*`` in channels.c). Each
reader keeps its own cursor, so any number of hosts can watch the same loop without disturbing
it or each other, and counts in ``lost`` what the loop overwrote before the reader got to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from .binding import CData, ffi, lib

if TYPE_CHECKING:
    from .host import Channels


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


Item = TypeVar("Item")


class _BroadcastReader(Generic[Item]):
    """A private cursor over one broadcast ring; counts what the loop overwrote before we read."""

    def __init__(self, ring: CData, slots: CData, slot_type: str, from_start: bool) -> None:
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

    def read(self, max_items: int | None = None) -> list[Item]:
        items: list[Item] = []
        while max_items is None or len(items) < max_items:
            if not lib.xrf_bcast_read(self._ring, self._slots, self._cursor, self._out, self._lost):
                break
            items.append(self._convert(self._out))
        return items

    def _convert(self, slot: CData) -> Item:  # pragma: no cover - overridden
        raise NotImplementedError


class TelemetryReader(_BroadcastReader[Telemetry]):
    def __init__(self, channels: Channels, from_start: bool = False) -> None:
        shm = channels.shm
        super().__init__(ffi.addressof(shm, "telem_ring"), shm.telem, "struct xrf_telemetry", from_start)
        self._codec = channels.xeno2ros_codec

    def _convert(self, t: CData) -> Telemetry:
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


class MonitorReader(_BroadcastReader[MonitorLine]):
    def __init__(self, channels: Channels, from_start: bool = False) -> None:
        shm = channels.shm
        super().__init__(ffi.addressof(shm, "monitor_ring"), shm.monitor, "struct xrf_monitor_line", from_start)

    def _convert(self, m: CData) -> MonitorLine:
        n = min(m.len, lib.XRF_MONITOR_TEXT)
        text = bytes(ffi.buffer(m.text, n)).decode("utf-8", "replace")
        return MonitorLine(cycle=m.hdr.cycle, t_ns=m.hdr.t_ns, text=text)
