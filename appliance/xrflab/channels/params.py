"""The parameter block of a loop's segment (rt_core's xrf/params.h), host side.

``read_table`` takes the loop's table once into our memory, checked by the C reader (count
bounded, names and numbers validated: the guest writes this memory); ``send_set`` writes one
pending set and ``wait_answer`` waits, bounded, for the loop to take it at a cycle boundary.
Names are resolved to indices by the caller from its own copy of the table; nothing read back
from the segment but the answer's seq (compared), its result (clamped) and cycle is used.
"""

from __future__ import annotations

import errno
import math
import time
from dataclasses import dataclass

from .binding import CData, c_str, ffi, lib
from .errors import ChannelsCorrupt

SOURCES = {lib.XRF_PARAM_SOURCE_DECLARED: "declared", lib.XRF_PARAM_SOURCE_20SIM: "20sim"}
ORIGINS = {lib.XRF_PARAMS_ORIGIN_NONE: "none", lib.XRF_PARAMS_ORIGIN_20SIM: "20sim"}
SET_MAX = int(lib.XRF_PARAM_SET_MAX)


@dataclass(frozen=True)
class ParamDesc:
    index: int
    name: str
    unit: str
    default: float
    min: float
    max: float
    has_range: bool
    source: str


@dataclass(frozen=True)
class ParamTable:
    origin: str
    params: tuple[ParamDesc, ...]


@dataclass(frozen=True)
class Answer:
    seq: int
    applied: bool
    cycle: int


def _block(shm: CData) -> CData:
    return ffi.addressof(shm, "params")


def read_table(shm: CData, name: str) -> ParamTable:
    """The loop's table (written before ready, constant for the run); ChannelsCorrupt if the
    block breaks its rules."""
    copy = ffi.new("struct xrf_params *")
    n = lib.xrf_params_table_read(_block(shm), copy)
    if n < 0:
        raise ChannelsCorrupt(f"{name}: the parameter table breaks its rules (count, names or values)")
    params = tuple(
        ParamDesc(
            index=i,
            name=c_str(copy.desc[i].name),
            unit=c_str(copy.desc[i].unit),
            default=float(copy.desc[i].initial),
            min=float(copy.desc[i].min),
            max=float(copy.desc[i].max),
            has_range=bool(copy.desc[i].flags & lib.XRF_PARAM_HAS_RANGE),
            source=SOURCES[int(copy.desc[i].source)],
        )
        for i in range(n)
    )
    return ParamTable(origin=ORIGINS[int(copy.origin)], params=params)


def read_values(shm: CData, table: ParamTable) -> list[float]:
    """The loop's current values (a non-finite one reads as its default), bounded by our table."""
    t = ffi.new("struct xrf_params *")
    t.count = len(table.params)
    for p in table.params:
        t.desc[p.index].initial = p.default
    out = ffi.new("double[]", max(1, len(table.params)))
    lib.xrf_params_values_read(_block(shm), t, out)
    return [float(out[i]) for i in range(len(table.params))]


def last_answer(shm: CData) -> int:
    """The seq of the set the loop answered last (0: none yet): a reader that remembers it knows
    cheaply when the values may have changed (the ROS 2 bridge follows the appliance's sets)."""
    return int(_block(shm).ack_seq)


def send_set(shm: CData, entries: list[tuple[int, float]]) -> int:
    """Writes one pending set (indices from our table, finite values); returns its seq.
    ValueError for an empty/oversized set or a non-finite value; BlockingIOError when a writer
    holds the block."""
    if not entries or len(entries) > SET_MAX or not all(math.isfinite(v) for _, v in entries):
        raise ValueError(f"a set holds 1..{SET_MAX} finite values")
    idx = ffi.new("uint32_t[]", [i for i, _ in entries])
    val = ffi.new("double[]", [v for _, v in entries])
    rc = int(lib.xrf_params_request(_block(shm), idx, val, len(entries)))
    if rc == -errno.EBUSY:
        raise BlockingIOError("the parameter block is held by another writer")
    if rc < 0:
        raise ValueError(f"the set was refused ({rc})")
    return rc


def answered(shm: CData, seq: int) -> Answer | None:
    result = ffi.new("int32_t *")
    cycle = ffi.new("uint64_t *")
    if not lib.xrf_params_answered(_block(shm), seq, result, cycle):
        return None
    return Answer(seq=seq, applied=result[0] == 0, cycle=int(cycle[0]))


def wait_answer(shm: CData, seq: int, timeout: float) -> Answer | None:
    """The loop's answer to set `seq`, polled (a loop takes a set within a cycle or two), or None
    after `timeout` s."""
    deadline = time.monotonic() + timeout
    pause = 0.0002
    while True:
        a = answered(shm, seq)
        if a is not None:
            return a
        if time.monotonic() >= deadline:
            return None
        time.sleep(pause)
        pause = min(pause * 2, 0.005)
