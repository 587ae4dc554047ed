"""Readers of the loop's broadcast rings: telemetry (one sample a cycle) and monitor lines.

The loop overwrites its rings without waiting for anyone (``xrf_bcast_*`` in channels.c). Each
reader keeps its own cursor, so any number of hosts can watch the same loop without disturbing
it or each other, and counts in ``lost`` what the loop overwrote before the reader got to it.
The ring's geometry is the one ``Channels`` took at open (``xrf_bcast_read_g``): a slot is
copied into our memory whole, and its sizes (``size``, ``len``) are bounded before use.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from ..msgdef import Codec
from .binding import CData, ffi, lib
from .errors import ChannelsCorrupt


class Mapped(Protocol):
    """What a reader takes from the ``Channels`` that opens it (host.py): the mapping, the geometry
    checked at open, the payload codec. A protocol, so the readers need not import ``Channels``
    (which imports them)."""

    @property
    def name(self) -> str: ...
    @property
    def shm(self) -> CData: ...
    @property
    def geom(self) -> CData: ...
    @property
    def xeno2ros_codec(self) -> Codec: ...


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

    def __init__(self, name: str, ring: CData, geom: CData, slots: CData, slot_type: str, from_start: bool) -> None:
        self._name = name
        self._ring = ring
        # A copy of its own: the reader may outlive the Channels' attributes it came from.
        self._geom = ffi.new("struct xrf_ring_geom *", {"slots": geom.slots, "slot_size": geom.slot_size})
        self._slots = slots
        # xrf_bcast_read_g copies geom.slot_size bytes into _out: Channels checked that it is
        # the slot type's size.
        assert geom.slot_size == ffi.sizeof(slot_type)
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
        """What was published since the last read, at most one ring's worth (or `max_items`): a
        loop that keeps moving its head cannot keep a reader here."""
        items: list[Item] = []
        limit = int(self._geom.slots) if max_items is None else min(max_items, int(self._geom.slots))
        while len(items) < limit:
            rc = lib.xrf_bcast_read_g(self._ring, self._geom, self._slots, self._cursor, self._out, self._lost)
            if rc < 0:
                head = int(lib.xrfpy_load_u64(ffi.addressof(self._ring, "head")))
                raise ChannelsCorrupt(
                    f"{self._name}: a ring's head went back from {self.cursor} to {head} (publications are never taken back)"
                )
            if rc == 0:
                break
            items.append(self._convert(self._out))
        return items

    def _convert(self, slot: CData) -> Item:  # pragma: no cover - overridden
        raise NotImplementedError


class TelemetryReader(_BroadcastReader[Telemetry]):
    def __init__(self, channels: Mapped, from_start: bool = False) -> None:
        shm = channels.shm
        super().__init__(
            channels.name,
            ffi.addressof(shm, "telem_ring"),
            ffi.addressof(channels.geom, "telem"),
            shm.telem,
            "struct xrf_telemetry",
            from_start,
        )
        self._codec = channels.xeno2ros_codec
        # The bench's channel count as xrf_shm_check took it at open (1..XRF_MAX_CHANNELS), never
        # the segment's word now: the loop may rewrite that.
        self._n = int(channels.geom.channels)

    def _convert(self, t: CData) -> Telemetry:
        payload = bytes(ffi.buffer(t.data, min(t.size, lib.XRF_MSG_MAX)))
        n = self._n
        return Telemetry(
            cycle=t.hdr.cycle,
            t_ns=t.hdr.t_ns,
            state=t.state,
            enc=list(t.enc)[:n],
            din=list(t.din)[: 2 * n],
            pwm=list(t.pwm)[:n],
            dout=list(t.dout)[:n],
            xeno2ros=self._codec.decode(payload) if len(payload) >= self._codec.size else {},
            ros2xeno_t_sent_ns=t.ros2xeno_t_sent_ns,
        )


class MonitorReader(_BroadcastReader[MonitorLine]):
    def __init__(self, channels: Mapped, from_start: bool = False) -> None:
        shm = channels.shm
        super().__init__(
            channels.name,
            ffi.addressof(shm, "monitor_ring"),
            ffi.addressof(channels.geom, "monitor"),
            shm.monitor,
            "struct xrf_monitor_line",
            from_start,
        )

    def _convert(self, m: CData) -> MonitorLine:
        n = min(m.len, lib.XRF_MONITOR_TEXT)
        text = bytes(ffi.buffer(m.text, n)).decode("utf-8", "replace")
        return MonitorLine(cycle=m.hdr.cycle, t_ns=m.hdr.t_ns, text=text)
