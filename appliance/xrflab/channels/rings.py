"""Readers of the loop's broadcast rings: telemetry (one sample a cycle) and monitor lines.

The loop overwrites its rings without waiting for anyone (``xrf_bcast_*`` in channels.c). Each
reader keeps its own cursor, so any number of hosts can watch the same loop without disturbing
it or each other, and counts in ``lost`` what the loop overwrote before the reader got to it.
The ring's geometry is the one ``Channels`` took at open (``xrf_bcast_read_g``): a slot is
copied into our memory whole, and its sizes (``size``, ``len``) are bounded before use.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar, overload

import numpy as np

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

    @property
    def slots(self) -> int:
        """How many publications the ring keeps: a reader that reads less often than the loop
        fills it loses the oldest (counted in `lost`)."""
        return int(self._geom.slots)

    def skip(self) -> None:
        """Move to the newest publication: what came before is not read, nor counted lost (a
        reader that starts following the ring again wants what is new, not a backlog)."""
        self._cursor[0] = lib.xrfpy_load_u64(ffi.addressof(self._ring, "head"))

    def _went_back(self) -> ChannelsCorrupt:
        """The error for a head the loop moved behind our cursor."""
        head = int(lib.xrfpy_load_u64(ffi.addressof(self._ring, "head")))
        return ChannelsCorrupt(
            f"{self._name}: a ring's head went back from {self.cursor} to {head} (publications are never taken back)"
        )

    def read(self, max_items: int | None = None) -> list[Item]:
        """What was published since the last read, at most one ring's worth (or `max_items`): a
        loop that keeps moving its head cannot keep a reader here."""
        items: list[Item] = []
        limit = int(self._geom.slots) if max_items is None else min(max_items, int(self._geom.slots))
        while len(items) < limit:
            rc = lib.xrf_bcast_read_g(self._ring, self._geom, self._slots, self._cursor, self._out, self._lost)
            if rc < 0:
                raise self._went_back()
            if rc == 0:
                break
            items.append(self._convert(self._out))
        return items

    def _convert(self, slot: CData) -> Item:  # pragma: no cover - overridden
        raise NotImplementedError


# numpy's and struct's names for each C integer type the ring's slots use (native byte order:
# the loop's).
_NP_TYPES = {
    "int8_t": "i1",
    "uint8_t": "u1",
    "int16_t": "i2",
    "uint16_t": "u2",
    "int32_t": "i4",
    "uint32_t": "u4",
    "int64_t": "i8",
    "uint64_t": "u8",
}
_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "i8": "q", "u8": "Q"}


def _leaf_fields(ctype: str) -> list[tuple[str, int, str, int | None]]:
    """(name, offset, numpy type, array length or None) of each leaf field of a C struct, in
    cffi's layout of it (the header stays the one definition): a nested struct's fields as
    `outer_inner`."""
    out: list[tuple[str, int, str, int | None]] = []

    def walk(t: Any, base: int, prefix: str) -> None:
        for name, f in t.fields:
            ft = f.type
            if ft.kind == "struct":
                walk(ft, base + f.offset, f"{prefix}{name}_")
            elif ft.kind == "array":
                out.append((prefix + name, base + f.offset, _NP_TYPES[ft.item.cname], ft.length))
            else:
                out.append((prefix + name, base + f.offset, _NP_TYPES[ft.cname], None))

    walk(ffi.typeof(ctype), 0, "")
    return out


def slot_dtype(ctype: str) -> np.dtype:
    """A numpy view of a C struct from cffi's layout of it: a nested struct's fields as
    `outer_inner`, arrays as subarrays."""
    fields = _leaf_fields(ctype)
    return np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [(f[2], f[3]) if f[3] is not None else f[2] for f in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": ffi.sizeof(ctype),
        }
    )


def slot_struct(ctype: str, bytes_fields: tuple[str, ...] = ()) -> tuple[struct.Struct, dict[str, int]]:
    """One struct.Struct that unpacks a whole C struct (cffi's layout of it, gaps as pad bytes)
    in one call, and where each leaf field starts in the tuple it gives (an array's items follow
    its first; a byte array named in `bytes_fields` is one bytes object). Why: a sample sent to a dashboard is one slot; numpy's per-field access of
    one row cost more than the rest of its conversion (issue 30 item 4)."""
    fmt, at, i = ["="], 0, 0
    where: dict[str, int] = {}
    for name, offset, np_type, length in sorted(_leaf_fields(ctype), key=lambda f: f[1]):
        if offset > at:
            fmt.append(f"{offset - at}x")
        width = int(np_type[1:])
        if length is None:
            fmt.append(_STRUCT_CODES[np_type])
            where[name], i = i, i + 1
        elif name in bytes_fields and width == 1:
            fmt.append(f"{length}s")
            where[name], i = i, i + 1
        else:
            fmt.append(f"{length}{_STRUCT_CODES[np_type]}")
            where[name], i = i, i + length
        at = offset + width * (length or 1)
    size = ffi.sizeof(ctype)
    if size > at:
        fmt.append(f"{size - at}x")
    s = struct.Struct("".join(fmt))
    assert s.size == size, (ctype, s.size, size)
    return s, where


_TELEMETRY_STRUCT = "struct xrf_telemetry"


@functools.cache
def _telemetry_layout() -> tuple[np.dtype, struct.Struct, dict[str, int]]:
    """The telemetry slot's numpy and struct views, made once per process (the layout is the
    header's, fixed when the binding was built)."""
    st, where = slot_struct(_TELEMETRY_STRUCT, ("data",))
    return slot_dtype(_TELEMETRY_STRUCT), st, where


class TelemetryBatch(Sequence[Telemetry]):
    """The samples one read took, as columns: `t_ns`, `cycle`, `enc` (the bench's channels) and
    `din` as Python lists made by numpy in one go, and each sample as a `Telemetry` (every
    field, the payload decoded) only when asked for (`batch[i]`, iterating: one struct unpack of
    its slot's bytes).

    Why: the reader takes every sample (50 a second for a RELbot) for the 3D view's recording,
    which needs three of its fields, and sends 30 a second to dashboards, none with nobody
    connected; converting each through cffi field by field (a list per array, the payload
    decoded) was most of an idle appliance's reading (issue 30 item 4). The slots are held as
    the bytes they were copied into (a numpy view over them is made only for the columns): a
    numpy copy of a structured array goes field by field, several times a memcpy's cost."""

    def __init__(self, raw: bytes, channels: int, codec: Codec) -> None:
        dtype, self._struct, self._where = _telemetry_layout()
        self._raw = raw
        self._size = self._struct.size
        self._len = len(raw) // self._size
        self._n = channels
        self._codec = codec
        self._items: dict[int, Telemetry] = {}
        self._dtype = dtype
        self._rows_made: np.ndarray | None = None
        # A few slots (the dashboards' batch: 1-2 per wake-up, 30 a second) are unpacked by
        # struct at once, each needed whole for the sample sent anyway: numpy's start-up per call
        # cost more than the unpacking (issue 30 item 4); a larger batch gets its columns by numpy.
        self._values: list[tuple[Any, ...]] | None = None
        if self._len <= SMALL_BATCH:
            self._values = [self._struct.unpack_from(raw, i * self._size) for i in range(self._len)]
            at = self._where["hdr_t_ns"]
            self.t_ns: list[int] = [v[at] for v in self._values]
        else:
            self.t_ns = self._rows["hdr_t_ns"].tolist()
        self._cycle: list[int] | None = None
        self._enc: list[list[int]] | None = None
        self._din: list[list[int]] | None = None

    @property
    def _rows(self) -> np.ndarray:
        if self._rows_made is None:
            self._rows_made = np.frombuffer(self._raw, dtype=self._dtype)  # read-only: over immutable bytes
        return self._rows_made

    @property
    def cycle(self) -> list[int]:
        if self._cycle is None:
            self._cycle = self._rows["hdr_cycle"].tolist()
        return self._cycle

    @property
    def enc(self) -> list[list[int]]:
        if self._enc is None:
            self._enc = self._rows["enc"][:, : self._n].tolist()
        return self._enc

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_ns, cycle, enc) as read-only numpy columns over the slots (enc: samples x the
        bench's channels), for whoever takes a batch in bulk (the 3D view's recording and model
        with nobody watching: issue 30 item 4), without a Python object per sample."""
        rows = self._rows
        return rows["hdr_t_ns"], rows["hdr_cycle"], rows["enc"][:, : self._n]

    @property
    def din(self) -> list[list[int]]:
        if self._din is None:
            self._din = self._rows["din"][:, : 2 * self._n].tolist()
        return self._din

    def __len__(self) -> int:
        return self._len

    @overload
    def __getitem__(self, i: int) -> Telemetry: ...
    @overload
    def __getitem__(self, i: slice) -> list[Telemetry]: ...

    def __getitem__(self, i: int | slice) -> Telemetry | list[Telemetry]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        item = self._items.get(i)
        if item is None:
            v = self._values[i] if self._values is not None else self._struct.unpack_from(self._raw, i * self._size)
            w, n = self._where, self._n
            enc, din, pwm, dout = w["enc"], w["din"], w["pwm"], w["dout"]
            payload = v[w["data"]][: min(v[w["size"]], lib.XRF_MSG_MAX)]
            item = Telemetry(
                cycle=v[w["hdr_cycle"]],
                t_ns=v[w["hdr_t_ns"]],
                state=v[w["state"]],
                enc=list(v[enc : enc + n]),
                din=list(v[din : din + 2 * n]),
                pwm=list(v[pwm : pwm + n]),
                dout=list(v[dout : dout + n]),
                xeno2ros=self._codec.decode(payload) if len(payload) >= self._codec.size else {},
                ros2xeno_t_sent_ns=v[w["ros2xeno_t_sent_ns"]],
            )
            self._items[i] = item
        return item


BATCH_SLOTS = 64  # slots copied per C buffer taken as bytes (42 KB of telemetry slots)
SMALL_BATCH = 4  # up to this many slots a TelemetryBatch unpacks by struct, not numpy


class TelemetryReader(_BroadcastReader[Telemetry]):
    def __init__(self, channels: Mapped, from_start: bool = False) -> None:
        shm = channels.shm
        super().__init__(
            channels.name,
            ffi.addressof(shm, "telem_ring"),
            ffi.addressof(channels.geom, "telem"),
            shm.telem,
            _TELEMETRY_STRUCT,
            from_start,
        )
        self._codec = channels.xeno2ros_codec
        # The bench's channel count as xrf_shm_check took it at open (1..XRF_MAX_CHANNELS), never
        # the segment's word now: the loop may rewrite that.
        self._n = int(channels.geom.channels)

        self._batch = ffi.new(_TELEMETRY_STRUCT + "[]", BATCH_SLOTS)

    def read(self, max_items: int | None = None) -> list[Telemetry]:
        return list(self.read_batch(max_items))

    def read_batch(self, max_items: int | None = None) -> TelemetryBatch:
        """What was published since the last read (at most one ring's worth, or `max_items`), as
        a TelemetryBatch: the slots are copied as they are (one C call each, as `read`), then
        taken as bytes a BATCH_SLOTS at a time."""
        limit = int(self._geom.slots) if max_items is None else min(max_items, int(self._geom.slots))
        parts: list[bytes] = []
        taken = filled = 0
        buf, size = self._batch, ffi.sizeof(_TELEMETRY_STRUCT)
        while taken < limit:
            rc = lib.xrf_bcast_read_g(self._ring, self._geom, self._slots, self._cursor, buf + filled, self._lost)
            if rc < 0:
                raise self._went_back()
            if rc == 0:
                break
            taken += 1
            filled += 1
            if filled == BATCH_SLOTS:
                parts.append(ffi.buffer(buf, filled * size)[:])
                filled = 0
        if filled or not parts:
            parts.append(ffi.buffer(buf, filled * size)[:])
        return TelemetryBatch(parts[0] if len(parts) == 1 else b"".join(parts), self._n, self._codec)


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
