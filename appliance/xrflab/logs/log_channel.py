"""One log channel of a run's shared memory, as the host writer reads it.

A loop has two lossless log channels, each a layout block (``*_meta``: the variables, the file
the loop names, who writes the file) and a single-producer ring of fixed-size records: the
student's logger (``log``) and the per-cycle timing records (``cycle_timing``, XRF_LOG_TIMING=1).
Everything here goes through rt_core's own functions via cffi (``xrf_log_meta_check``,
``xrf_spsc_peek_run_g``, ``xrf_spsc_release_g``, the atomic loads, ``xrf_logfile_header``), so the
host reads the ring and composes a segment header exactly as the loop's own writer does. The
loop never waits for the host: what the host does not release in time, the loop counts as lost.

A channel's layout may change while the loop runs (the logger set up again): its
``generation`` counts the layouts, and each one starts a new segment of the file
(``SegmentLayout``). The loop is not trusted with any of it: when the generation changes, the
layout is copied once into our memory and checked (``take_layout``: writer, variables inside
the record, the ring's geometry what the logger sets, the consumer's position); the ring is
then read with that copy's geometry and our own read position, and a head that claims more
than the ring holds is ``ChannelsCorrupt``. No size or offset is read from the segment again.
"""

from __future__ import annotations

import errno
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import logformat

if TYPE_CHECKING:
    from ..channels import Channels

# Layouts a run's channel may publish: a logger publishes one (XenoFrtLogger::publish, once per
# logger object). A loop that keeps bumping the generation would have the writer start a new
# segment (a header of up to 56 KiB) at every drain.
MAX_LAYOUTS = 100

# Log channels of the shared memory: (meta, ring, slots) field names.
SOURCES = {
    "log": ("log_meta", "log_ring", "log_data"),  # the student's XenoFrtLogger
    "cycle_timing": ("timing_meta", "timing_ring", "timing"),
}  # XRF_LOG_TIMING=1


@dataclass(frozen=True)
class SegmentLayout:
    """What the loop published for a segment: the records' stride and type, and its file."""

    stride: int
    dtype: np.dtype | None  # None: a layout the reader cannot decode (no live records then)
    path: str  # the file as the loop named it (untrusted: runfolder.confine)
    file_mode: int


class LogChannel:
    def __init__(self, ch: Channels, source: str) -> None:
        from .. import channels as chmod

        self._ch = ch
        self.source = source
        self._meta_field, self._ring_field, self._slots_field = SOURCES[source]
        self._lib, self._ffi = chmod.lib, chmod.ffi
        # The space the layout gives this channel's slots: what its geometry must fit.
        self._capacity = int(self._ffi.sizeof(getattr(ch.shm, self._slots_field)))
        # Ours, never the segment's: the layout as checked, its ring's geometry, our read position.
        self._meta = self._ffi.new("struct xrf_log_meta *")
        self._geom = self._ffi.new("struct xrf_ring_geom *")
        self._tail = self._ffi.new("uint64_t *")
        self._first = self._ffi.new("void **")
        self.taken = False  # a layout was taken (and checked)
        self.layouts = 0  # how many

    # cffi has no static types for the segment's structs: these stay inside this module.
    def _meta_in_segment(self) -> Any:
        return self._ffi.addressof(self._ch.shm, self._meta_field)

    def _ring_in_segment(self) -> Any:
        return self._ffi.addressof(self._ch.shm, self._ring_field)

    def ready(self) -> bool:
        """The loop has published the channel's layout."""
        return bool(self._lib.xrfpy_load_u32(self._ffi.addressof(self._meta_in_segment(), "ready")))

    def generation(self) -> int:
        """The generation the segment says now (only compared with the taken one's)."""
        return int(self._lib.xrfpy_load_u64(self._ffi.addressof(self._meta_in_segment(), "generation")))

    @property
    def taken_generation(self) -> int:
        return int(self._meta.generation) if self.taken else 0

    def take_layout(self) -> SegmentLayout | None:
        """Copy the channel's layout and check it (xrf_log_meta_check): the layout, or None when
        it is not published or changed during the copy (try again later). ChannelsCorrupt when
        it is not one the runtime's logger publishes; the previous layout is then kept."""
        from ..channels import ChannelsCorrupt

        meta = self._ffi.new("struct xrf_log_meta *")
        geom = self._ffi.new("struct xrf_ring_geom *")
        tail = self._ffi.new("uint64_t *")
        rc = self._lib.xrf_log_meta_check(
            self._meta_in_segment(), self._ring_in_segment(), self._capacity, meta, geom, tail
        )
        if rc == -errno.EAGAIN:
            return None
        if rc != 0:
            raise ChannelsCorrupt(
                f"{self._ch.name}: the {self.source} channel's layout is not one the logger publishes "
                f"(nvars {int(meta.nvars)}, record_size {int(meta.record_size)}, writer {int(meta.writer)}; "
                f"ring {int(self._ring_in_segment().slots)} slots of {int(self._ring_in_segment().slot_size)} bytes "
                f"in {self._capacity})"
            )
        self.layouts += 1
        if self.layouts > MAX_LAYOUTS:
            raise ChannelsCorrupt(
                f"{self._ch.name}: the {self.source} channel's layout changed {self.layouts} times "
                f"(a logger publishes one)"
            )
        self._meta, self._geom, self._tail, self.taken = meta, geom, tail, True
        return self.layout()

    def host_writes(self) -> bool:
        """The taken layout asks the host to write the file (XRF_LOG_WRITER=host)."""
        return self.taken and int(self._meta.writer) == self._lib.XRF_LOG_WRITER_HOST

    def slot_size(self) -> int:
        """The record stride of the taken layout (0 before one is taken)."""
        return int(self._geom.slot_size) if self.taken else 0

    def slots(self) -> int:
        """The ring's slots in the taken layout (0 before one is taken)."""
        return int(self._geom.slots) if self.taken else 0

    def dropped(self) -> int:
        """Records the loop could not put in the ring (it was full): the loop's count, a number."""
        return int(self._lib.xrfpy_load_u64(self._ffi.addressof(self._ring_in_segment(), "dropped")))

    def peek_run(self) -> tuple[memoryview, int] | None:
        """The longest run of ready records that is contiguous in the ring (bytes, count), left
        in place until ``release``; None when the ring is empty, no layout is taken, or the loop
        has published a new layout since (take it first). ChannelsCorrupt when the ring's head
        claims more records than the ring holds, or lies behind our read position."""
        from ..channels import ChannelsCorrupt

        if not self.taken:
            return None
        ring = self._ring_in_segment()
        slots = getattr(self._ch.shm, self._slots_field)
        n = self._lib.xrf_spsc_peek_run_g(ring, self._geom, slots, self._tail[0], self._first)
        if n == 0:
            return None
        if n < 0:
            if self.generation() != self.taken_generation:
                return None  # re-published (the ring was set up again): the new layout first
            head = int(self._lib.xrfpy_load_u64(self._ffi.addressof(ring, "head")))
            raise ChannelsCorrupt(
                f"{self._ch.name}: the {self.source} ring's head {head} is not within "
                f"{int(self._geom.slots)} records of the read position {int(self._tail[0])}"
            )
        # n <= slots - (tail mod slots): the bytes lie inside the ring's slots (xrf_spsc_peek_run_g).
        return memoryview(self._ffi.buffer(self._first[0], n * int(self._geom.slot_size))), n

    def release(self, n: int) -> None:
        """Give the oldest `n` records' slots back to the loop."""
        self._lib.xrf_spsc_release_g(self._ring_in_segment(), self._tail, n)

    def layout(self) -> SegmentLayout:
        """The taken layout (its copy) as the writer and the live stream use it."""
        from .reader import make_variables, record_dtype

        m = self._meta
        stride = self.slot_size()
        variables = []
        for i in range(min(int(m.nvars), self._lib.XRF_LOG_VARS_MAX)):
            v = m.vars[i]
            variables.append(
                (
                    self._ffi.string(v.name, self._lib.XRF_NAME_MAX).decode("utf-8", "replace"),
                    int(v.type),
                    int(v.offset),
                )
            )
        dtype: np.dtype | None
        try:
            vs = make_variables(
                Path("<ring>"),
                [v[0] for v in variables],
                [v[1] for v in variables],
                [v[2] for v in variables],
                tuple(name for name, _, _ in logformat.RECORD_HEADER),
            )
            dtype = record_dtype(vs, stride)
        except Exception:
            dtype = None
        return SegmentLayout(
            stride=stride,
            dtype=dtype,
            path=self._ffi.string(m.path, self._lib.XRF_PATH_MAX).decode("utf-8", "replace"),
            file_mode=int(m.file_mode) or 0o644,
        )

    def segment_header(
        self, identity: dict[str, str], start_unix_ns: int | None = None, start_mono_ns: int | None = None
    ) -> bytes:
        """The header of a segment of the channel's taken layout, starting now (or at the given
        clocks): rt_core's composer with what the loop's writer gives it, the program name, pid and
        cycle frequency from the info block Channels took at open, and the run's identity (what
        the loop's environment says: live.loop_env). Takes the layout first if none is yet."""
        if not self.taken:
            self.take_layout()
        info = self._ch.info
        return logformat.segment_header(
            self._meta,
            self.slot_size(),
            program=str(info["program"]),
            pid=int(info["pid"]),
            cycle_freq=int(info["cycle_freq"]),
            start_unix_ns=time.time_ns() if start_unix_ns is None else start_unix_ns,
            start_mono_ns=time.monotonic_ns() if start_mono_ns is None else start_mono_ns,
            project=identity.get("project", ""),
            build=identity.get("build", ""),
            run=identity.get("run", ""),
        )
