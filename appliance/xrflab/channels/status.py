"""The loop's status block read as Python values: ``Status`` and the stages' ``Histogram``.

The loop writes the block every cycle under a seqlock (``xrf_status_read`` in channels.c retries
a torn read); a reader copies it out whole and converts the copy, so one snapshot never mixes two
cycles. ``read_status`` gives up when the block stays locked: a loop that died mid-write (or one
that flips the lock on purpose: the tries are bounded, 20 ms in all). Every field is a number
of a fixed width; the strings are cut at their array's end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from .binding import CData, c_str, ffi, lib
from .errors import ChannelsError
from .names import state_name

# Attempts (up to XRF_STATUS_TRIES copies each in C, a fraction of a millisecond) for at most this
# long, a short sleep between them: enough for a loop descheduled while it writes the block (a
# busy host, valgrind), short enough that a loop holding or flipping the lock on purpose does
# not hold the caller (the event loop, for the heartbeat and the state) for long.
_STATUS_READ_S = 0.02
_STATUS_RETRY_SLEEP_S = 0.0002


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


def read_status(shm: CData, name: str) -> CData:
    """A consistent copy of the segment's status block (a ``struct xrf_status *``)."""
    out = ffi.new("struct xrf_status *")
    deadline = time.monotonic() + _STATUS_READ_S
    while True:
        if lib.xrf_status_read(ffi.addressof(shm, "status"), out) == 0:
            return out
        if time.monotonic() >= deadline:
            break
        time.sleep(_STATUS_RETRY_SLEEP_S)
    raise ChannelsError(f"{name}: status block stays locked (loop died while writing it?)")


def status_from_struct(s: CData) -> Status:
    return Status(
        state=s.state,
        state_name=state_name(s.state),
        last_error=s.last_error,
        last_cmd=s.last_cmd,
        last_rejected_cmd=s.last_rejected_cmd,
        reject_code=s.reject_code,
        reject_reason=c_str(s.reject_reason),
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


def histogram_from_struct(h: CData) -> Histogram:
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
