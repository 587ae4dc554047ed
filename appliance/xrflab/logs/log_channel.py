"""One log channel of a run's shared memory, as the host writer reads it.

A loop has two lossless log channels, each a layout block (``*_meta``: the variables, the file
the loop names, who writes the file) and a single-producer ring of fixed-size records: the
student's logger (``log``) and the per-cycle timing records (``cycle_timing``, XRF_LOG_TIMING=1).
Everything here goes through rt_core's own functions via cffi (``xrf_spsc_peek_run``,
``xrf_spsc_release_n``, the atomic loads, ``xrf_logfile_header``), so the host reads the ring and
composes a segment header exactly as the loop's own writer does. The loop never waits for the
host: what the host does not release in time, the loop counts as lost.

A channel's layout may change while the loop runs (the logger set up again): its
``generation`` counts the layouts, and each one starts a new segment of the file
(``SegmentLayout``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import logformat

if TYPE_CHECKING:
    from ..channels import Channels

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
        self._count = self._ffi.new("uint32_t *")

    # cffi has no static types for the segment's structs: these two stay inside this module.
    def _meta(self) -> Any:
        return getattr(self._ch.shm, self._meta_field)

    def _ring(self) -> Any:
        return getattr(self._ch.shm, self._ring_field)

    def ready(self) -> bool:
        """The loop has published the channel's layout."""
        return bool(self._lib.xrfpy_load_u32(self._ffi.addressof(self._meta(), "ready")))

    def host_writes(self) -> bool:
        """The loop asked the host to write the file (XRF_LOG_WRITER=host)."""
        if not self.ready():
            return False
        return int(self._meta().writer) == self._lib.XRF_LOG_WRITER_HOST

    def generation(self) -> int:
        return int(self._lib.xrfpy_load_u64(self._ffi.addressof(self._meta(), "generation")))

    def slot_size(self) -> int:
        return int(self._ring().slot_size)

    def dropped(self) -> int:
        """Records the loop could not put in the ring (it was full)."""
        return int(self._ring().dropped)

    def peek_run(self, stride: int) -> tuple[memoryview, int] | None:
        """The longest run of ready records that is contiguous in the ring (bytes, count), left
        in place until ``release``; None when the ring is empty."""
        ring = self._ffi.addressof(self._ch.shm, self._ring_field)
        slots = getattr(self._ch.shm, self._slots_field)
        p = self._lib.xrf_spsc_peek_run(ring, slots, self._count)
        if p == self._ffi.NULL:
            return None
        n = int(self._count[0])
        return memoryview(self._ffi.buffer(p, n * stride)), n

    def release(self, n: int) -> None:
        """Give the oldest `n` records' slots back to the loop."""
        self._lib.xrf_spsc_release_n(self._ffi.addressof(self._ch.shm, self._ring_field), n)

    def layout(self) -> SegmentLayout:
        from .reader import make_variables, record_dtype

        m = self._meta()
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
        """The header of a segment of the channel's current layout, starting now (or at the given
        clocks): rt_core's composer with what the loop's writer gives it, the program name, pid and
        cycle frequency from the loop's info block (the program's bytes as they are there) and
        the run's identity (what the loop's environment says: live.loop_env)."""
        info = self._ch.shm.info
        return logformat.segment_header(
            self._ffi.addressof(self._ch.shm, self._meta_field),
            self.slot_size(),
            program=self._ffi.string(info.program, self._lib.XRF_NAME_MAX),
            pid=int(info.pid),
            cycle_freq=int(info.cycle_freq),
            start_unix_ns=time.time_ns() if start_unix_ns is None else start_unix_ns,
            start_mono_ns=time.monotonic_ns() if start_mono_ns is None else start_mono_ns,
            project=identity.get("project", ""),
            build=identity.get("build", ""),
            run=identity.get("run", ""),
        )
