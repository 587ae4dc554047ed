"""The loop's status block read as Python values: ``Status`` and the stages' ``Histogram``.

The loop writes the block every cycle under a seqlock (``xrf_status_read`` in channels.c retries
a torn read); a reader copies it out whole and converts the copy, so one snapshot never mixes two
cycles. ``StatusReader`` reads it for one mapping: a read that finds the block locked spins a
fraction of a millisecond at most (it runs on the appliance's event loop), then gives the last
good copy ("not now": the next tick asks again). A legitimate loop preempted in the middle of its
write (a busy host, a vCPU steal, no RT priority) holds the lock for as long as it is off the CPU,
which can be tens of milliseconds; it makes no progress meanwhile. So the block is only called
corrupt when the loop is evidently running while it stays locked (its cycle count moved on by
``LOCKED_CYCLES`` while the sequence number stayed the same odd value: a real writer finishes a
status write within its cycle), or after ``LOCKED_LIMIT_S`` of failed reads in a row that each
found it odd (a loop that flips the parity on purpose). A loop that does not progress at all is the hang detectors' (the
safety watcher's hang timeout, the grading runner's stall limit), well within that bound. Every
field is a number of a fixed width; the strings are cut at their array's end.
"""

from __future__ import annotations

import functools
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .binding import CData, c_str, ffi, lib
from .errors import ChannelsCorrupt, StatusBusy
from .names import STAGE_NAMES, state_name

# A read that finds the block locked tries again (XRF_STATUS_TRIES copies each in C, a few
# microseconds when the seq is odd) for at most this long, yielding the CPU between tries (to a
# writer that waits for it; a sleep instead overshoots by milliseconds on a busy host): a loop on
# a CPU finishes its write in microseconds. On the event loop this is the longest one read holds
# it; while the block stays locked, later reads try once without spinning (StatusReader).
STATUS_SPIN_S = 0.0005
# The loop's cycle count moving on by this many while the status seq stays at one odd value: no
# writer of ours does that (the count is written inside the same write), the loop is running and
# the lock is held on purpose.
LOCKED_CYCLES = 8
# Failed reads in a row for this long are corrupt whatever the counts say (a loop that sets the
# seq odd once inverts the lock: it is odd between writes from then on, a new value each cycle).
# Longer than the hang detectors' limits (watcher 200 ms, grading stall 3 s), which end a loop
# that is not cycling at all first, as hung.
LOCKED_LIMIT_S = 5.0


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


def read_status(shm: CData, spin_s: float = STATUS_SPIN_S) -> CData | None:
    """A consistent copy of the segment's status block (a ``struct xrf_status *``), or None when
    the block stayed locked for `spin_s` (0: one try): a write in progress, ask again later."""
    out = ffi.new("struct xrf_status *")
    status = ffi.addressof(shm, "status")
    deadline = time.monotonic() + spin_s
    while True:
        if lib.xrf_status_read(status, out) == 0:
            return out
        if time.monotonic() >= deadline:
            return None
        os.sched_yield()


class StatusReader:
    """The status block of one mapping, read without holding the caller: ``read()`` gives a
    fresh copy, or while the block is locked the last good one (StatusBusy if there is none
    yet), and ChannelsCorrupt once the lock is evidently held on purpose (module docstring).
    Safe from several threads (the event loop, a command's wait, the host log writer)."""

    def __init__(self, shm: CData, name: str, clock: Callable[[], float] = time.monotonic) -> None:
        self._shm = shm
        self._name = name
        self._clock = clock
        self._lock = threading.Lock()
        self._last: CData | None = None
        self._locked_since: float | None = None  # the first of the failed reads in a row
        self._odd_seq: int | None = None  # the odd seq those reads last saw, and the loop's
        self._odd_cycles = 0  # cycle count when it was first seen
        self._corrupt = ""
        self.copies = 0  # consistent copies made (tests: a reader's copies per use, issue 30 item 4)

    def read(self) -> CData:
        s = self.read_fresh()
        if s is not None:
            return s
        with self._lock:
            if self._last is None:
                raise StatusBusy(f"{self._name}: the loop is writing its status block; ask again")
            return self._last

    def read_fresh(self) -> CData | None:
        """A copy of the block as it is now, or None ("not now"): for a caller that acts on the
        loop's position (the grading runner's events), where the last copy would mislead."""
        if self._corrupt:
            raise ChannelsCorrupt(self._corrupt)
        # In a run of failed reads only one try each: a block held locked on purpose costs the
        # caller a few microseconds a read, not a spin every time.
        s = read_status(self._shm, 0.0 if self._locked_since is not None else STATUS_SPIN_S)
        with self._lock:
            if s is not None:
                self._last = s
                self.copies += 1
                self._locked_since, self._odd_seq = None, None
                return s
            self._judge_locked()
            return None

    def _judge_locked(self) -> None:
        """One more failed read: corrupt (raise) if the loop cycles on while the block stays
        locked at one seq, or after LOCKED_LIMIT_S of failed reads that each found it odd."""
        now = self._clock()
        status = ffi.addressof(self._shm, "status")
        # Relaxed views of two words the loop writes (outside any copy: only compared).
        seq = int(lib.xrfpy_load_u32(ffi.addressof(status, "seq")))
        cycles = int(lib.xrfpy_load_u64(ffi.addressof(status, "cycles")))
        if not seq & 1:
            # Not locked, only busy: a loop writing back to back (simulated time runs its cycles
            # flat out, each shorter than a copy) changed it under every copy. Not a lock.
            self._locked_since, self._odd_seq = None, None
            return
        if self._locked_since is None:
            self._locked_since = now
        if seq != self._odd_seq:
            self._odd_seq, self._odd_cycles = seq, cycles
        elif (ran := (cycles - self._odd_cycles) % (1 << 64)) >= LOCKED_CYCLES:
            self._give_up(f"status block stays locked (seq {seq}) while the loop ran {ran} cycles")
        if now - self._locked_since >= LOCKED_LIMIT_S:
            self._give_up(f"status block stays locked ({now - self._locked_since:.1f} s of reads)")

    def _give_up(self, why: str) -> None:
        self._corrupt = f"{self._name}: {why}"
        raise ChannelsCorrupt(self._corrupt)


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


def state_key_of(s: CData) -> tuple[int, int, bool, int]:
    """(state, cmd_rejected, running, last_error) of a status copy: what decides whether the
    dashboards' `state` message changed, without converting the rest of it."""
    return int(s.state), int(s.cmd_rejected), bool(s.running), int(s.last_error)


def histograms_of(s: CData) -> dict[str, Histogram]:
    """Every stage's Histogram of a status copy, by STAGE_NAMES."""
    return {name: histogram_from_struct(s.hist[i]) for i, name in enumerate(STAGE_NAMES)}


def timing_words_of(s: CData) -> tuple[dict[str, int], np.ndarray]:
    """Of a status copy: the counters the run's timing series keeps (cycles, missed, log_written,
    log_lost) and the stages' histograms as words (hist_words); their figures (count, sum, min,
    max, percentiles: the values each Histogram gives) are made from these by stage_figures_many,
    several samples together (logs/timing_series.py)."""
    counters = {
        "cycles": int(s.cycles),
        "missed": int(s.missed),
        "log_written": int(s.log_written),
        "log_lost": int(s.log_lost),
    }
    return counters, hist_words(s)


@functools.cache
def _bucket_lows() -> np.ndarray:
    """Every bucket's lower edge (ns), from rt_core's own function, once."""
    return np.array([lib.xrf_hist_bucket_low(b) for b in range(lib.XRF_HIST_BUCKETS)], dtype=np.int64)


def histogram_from_struct(h: CData) -> Histogram:
    # The buckets as one array (the copy's bytes), the non-empty ones found by numpy: indexing
    # 512 cffi items per stage cost ~0.2 ms a stage, eight stages a second in the run's timing
    # series (issue 30 item 4).
    buckets = np.frombuffer(ffi.buffer(h.buckets), dtype=np.uint64)
    used = np.flatnonzero(buckets)
    edges = _bucket_lows()[used].tolist()
    counts = buckets[used].tolist()
    count = h.count
    return Histogram(
        count=count,
        min=h.min_ns if count else 0,
        max=h.max_ns,
        mean=h.sum_ns / count if count else 0.0,
        edges=edges,
        counts=counts,
    )


# struct xrf_hist is count, sum_ns, min_ns, max_ns, then the buckets: all 64-bit words, no padding.
_HIST_WORDS = 4 + lib.XRF_HIST_BUCKETS
assert ffi.sizeof("struct xrf_hist") == 8 * _HIST_WORDS


@dataclass(frozen=True)
class StageFigures:
    """One stage's figures from a status copy, as its Histogram gives them (histogram_from_struct):
    `percentiles` in the order asked for, each Histogram.percentile's value."""

    count: int
    sum_ns: int
    min_ns: int
    max_ns: int
    percentiles: tuple[int, ...]


def hist_words(s: CData) -> np.ndarray:
    """A copy of the stages' histograms of a status copy `s` as 64-bit words, a row per stage
    (count, sum_ns, min_ns, max_ns, the buckets): what stage_figures_of takes, kept apart from
    the status copy (the host writer takes them once a second and makes the lines every few)."""
    return np.frombuffer(ffi.buffer(s.hist), dtype=np.int64).reshape(-1, _HIST_WORDS).copy()


def stage_figures_of(words: np.ndarray, percentiles: tuple[float, ...]) -> list[StageFigures]:
    """Every stage's count, sum, min, max and `percentiles` from its histogram's words (hist_words),
    in STAGE_NAMES' order: the same values as histogram_from_struct(...).percentile(p), without a
    Python list of buckets per stage. One status copy's: stage_figures_many of one."""
    return stage_figures_many(words[None], percentiles)[0]


def stage_figures_many(words: np.ndarray, percentiles: tuple[float, ...]) -> list[list[StageFigures]]:
    """stage_figures_of for several copies at once: `words` stacked (copies, stages, words), the
    figures of every copy's stages in one numpy pass. The run's timing series makes the lines of
    the samples of several seconds together (logs/timing_series.py, at the host writer's drains):
    a pass per sample cost each drain four times numpy's per-call overhead, most of the idle
    writer thread's CPU (issue 30 item 4, session 16). Values are the loop's words as int64 (a loop
    writing more than 2**63 gets its own nonsense back; nothing is indexed by them)."""
    for p in percentiles:
        if not 0 <= p <= 100:
            raise ValueError("percentile must be within 0..100")
    copies, stages = words.shape[0], words.shape[1]
    rows = words.reshape(copies * stages, _HIST_WORDS)
    head = rows[:, :4]  # count, sum_ns, min_ns, max_ns
    counts, mins, maxs = head[:, 0:1], head[:, 2:3], head[:, 3:4]
    cum = np.cumsum(rows[:, 4:], axis=1)
    # The first bucket whose running count reaches the rank (and is not 0: p = 0 is the first
    # non-empty bucket): the number of buckets before it, all stages and percentiles at once.
    ranks = np.maximum(counts * (np.array(percentiles, dtype=np.float64) / 100.0), 0.5)
    first = (cum[:, None, :] < ranks[:, :, None]).sum(axis=2)
    buckets = cum.shape[1]
    # Clamped to [min, max] as Histogram.percentile does; none (the buckets add up to less than
    # the count): max; an empty stage: 0.
    edge = np.minimum(np.maximum(_bucket_lows()[np.minimum(first, buckets - 1)], mins), maxs)
    values = np.where(counts != 0, np.where(first < buckets, edge, maxs), 0).tolist()
    figures = [
        StageFigures(count=c, sum_ns=sm, min_ns=mn if c else 0, max_ns=mx, percentiles=tuple(v))
        for (c, sm, mn, mx), v in zip(head.tolist(), values)
    ]
    return [figures[i * stages : (i + 1) * stages] for i in range(copies)]
