"""The status block's seqlock as the host reads it (channels/status.py): a locked block never holds
a reader (it gets the last good copy, "not now"), a loop stopped mid-write is not corrupt however
long it stays stopped under the hang detectors' limits, and a block kept locked while the loop runs
on is (at once when its seq stays put, after LOCKED_LIMIT_S when a flipped lock moves it on).

Played from Python on a real segment (create_for_test, LoopSide): the loop side writes the block
with channels.c's own writer functions. A real loop stopped in the middle of its status write:
tests/rt_core/test_status_stall.py.
"""

from __future__ import annotations

import pytest

from xrf_testing.testloop import LoopSide
from xrflab import channels
from xrflab.channels import Channels, ChannelsCorrupt, StatusBusy, ffi, lib
from xrflab.channels.status import LOCKED_CYCLES, LOCKED_LIMIT_S, StatusReader


def open_write(ch: Channels) -> None:
    """The loop's status write begun and not finished: seq odd, as a loop preempted in it."""
    lib.xrf_status_write_begin(ffi.addressof(ch.shm, "status"))


def close_write(ch: Channels) -> None:
    lib.xrf_status_write_end(ffi.addressof(ch.shm, "status"))


class Clock:
    """A monotonic clock the test moves (the reader's limit in seconds, without waiting them out)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_a_loop_stopped_mid_write_gives_the_last_copy_until_it_finishes(ch: Channels) -> None:
    loop = LoopSide(ch)
    loop.count_cycle(5)
    assert ch.status().cycles == 5
    clock = Clock()
    reader = StatusReader(ch.shm, ch.name, clock)
    assert reader.read().cycles == 5
    open_write(ch)
    ch.shm.status.cycles = 6  # stored inside the open write, as endCycle does
    # Stopped in it for far longer than the old 20 ms window (and up to just under the absolute
    # limit): each read is "not now" with the last good copy, never corrupt.
    for _ in range(50):
        clock.now += (LOCKED_LIMIT_S * 0.99) / 50
        assert reader.read().cycles == 5
        assert ch.status().cycles == 5
    close_write(ch)
    assert reader.read().cycles == 6 and ch.status().cycles == 6
    # The run of failed reads ended with the write: a new stop starts counting afresh.
    open_write(ch)
    clock.now += LOCKED_LIMIT_S * 0.99
    assert reader.read().cycles == 6
    close_write(ch)


def test_a_loop_that_cycles_on_with_its_status_locked_is_corrupt(ch: Channels) -> None:
    loop = LoopSide(ch)
    loop.count_cycle(100)
    assert ch.status().cycles == 100
    ch.shm.status.seq = 1001  # a hostile loop holds the lock at one odd value
    assert ch.status().cycles == 100  # not now: the last copy
    ch.shm.status.cycles = 100 + LOCKED_CYCLES - 1
    assert ch.status().cycles == 100  # a cycle count written during one write moves by one
    ch.shm.status.cycles = 100 + LOCKED_CYCLES
    with pytest.raises(ChannelsCorrupt, match="stays locked"):
        ch.status()
    # The verdict stands: every later read (the state, histograms, commands) says so.
    ch.shm.status.seq = 1002
    with pytest.raises(ChannelsCorrupt, match="stays locked"):
        ch.state_key()
    with pytest.raises(ChannelsCorrupt):
        ch.histograms()


def test_a_flipped_lock_is_corrupt_after_the_limit(ch: Channels) -> None:
    """seq set odd once: every complete write leaves it odd, a new value each cycle. The same-seq
    rule never fires (a legitimate writer stuck twice looks the same); the time limit does."""
    LoopSide(ch).count_cycle(3)
    clock = Clock()
    reader = StatusReader(ch.shm, ch.name, clock)
    assert reader.read().cycles == 3
    ch.shm.status.seq += 1  # odd from now on between writes
    status = ffi.addressof(ch.shm, "status")
    t_end = clock.now + LOCKED_LIMIT_S
    while clock.now + 0.1 < t_end:
        for _ in range(LOCKED_CYCLES + 2):  # the runtime's writes: +2 each, odd again
            lib.xrf_status_write_begin(status)
            ch.shm.status.cycles += 1
            lib.xrf_status_write_end(status)
        assert ch.shm.status.seq & 1
        assert reader.read().cycles == 3
        clock.now += 0.1
    clock.now = t_end
    with pytest.raises(ChannelsCorrupt, match="stays locked"):
        reader.read()


def test_a_loop_writing_back_to_back_is_busy_not_locked(ch: Channels) -> None:
    """Simulated time runs the loop's cycles flat out, each shorter than a copy of the block: a
    copy can fail for seconds without the block being locked (seq even between writes). Never
    corrupt; fresh_status says "not now", status the last copy."""
    LoopSide(ch).count_cycle(3)
    clock = Clock()
    reader = StatusReader(ch.shm, ch.name, clock)
    assert reader.read().cycles == 3
    status = ffi.addressof(ch.shm, "status")
    for _ in range(100):
        # What the reader sees of a write racing each copy: the seq moved on, even.
        lib.xrf_status_write_begin(status)
        ch.shm.status.cycles += 1
        lib.xrf_status_write_end(status)
        ch.shm.status.seq += 2  # as if a write completed under the copy
        clock.now += LOCKED_LIMIT_S / 10
        # Plays the failed copy: the reader's own judgement of what it found.
        reader._judge_locked()  # noqa: SLF001 - the verdict on a failed read, without the race
    assert reader.read().cycles == ch.shm.status.cycles  # not locked: read fine once it is quiet


def test_fresh_status_is_none_while_locked(ch: Channels) -> None:
    LoopSide(ch).count_cycle(4)
    assert ch.fresh_status() is not None
    open_write(ch)
    assert ch.fresh_status() is None and ch.status().cycles == 4
    close_write(ch)
    fresh = ch.fresh_status()
    assert fresh is not None and fresh.cycles == 4


def test_no_copy_yet_is_busy_not_corrupt(ch: Channels) -> None:
    open_write(ch)
    reader = StatusReader(ch.shm, ch.name, Clock())
    with pytest.raises(StatusBusy):
        reader.read()
    close_write(ch)
    assert reader.read().running == 1


def test_a_command_waits_through_a_status_write_in_progress(ch: Channels) -> None:
    loop = LoopSide(ch)
    ticket = ch.send_command("initialise")
    open_write(ch)
    # The loop handled it, but its status write is not finished: not yet known, no error.
    with pytest.raises(channels.CommandTimeout, match="not handled"):
        ch.wait_command(ticket, timeout=0.05)
    close_write(ch)
    assert loop.handle_commands() == 1
    assert ch.wait_command(ticket, timeout=2).accepted
