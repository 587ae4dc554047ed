"""Passing a command to the loop and learning what it made of it.

A command goes into the segment's command ring (``xrf_cmd_send``) and gets a ticket; the loop
handles it at its next command stage and writes the outcome into a small table of results in the
status block, indexed by ticket. A host waits for ``cmd_done`` to reach its ticket and reads its
slot — unless so many commands were handled since that the slot was reused.
"""

from __future__ import annotations

import errno
import time
from collections.abc import Callable
from dataclasses import dataclass

from .binding import CData, c_str, ffi, lib
from .errors import ChannelsCorrupt, ChannelsError, CommandRingFull, CommandTimeout, StatusBusy
from .names import command_number, state_name
from .status import status_from_struct


@dataclass(frozen=True)
class CommandResult:
    ticket: int
    accepted: bool
    state: int
    state_name: str
    reason: str


def send(shm: CData, name: str, cmd: str | int, source: int) -> int:
    """Queue a command in segment ``shm`` (called ``name`` in errors); returns its ticket."""
    number = command_number(cmd)
    ticket = lib.xrf_cmd_send(ffi.addressof(shm, "cmd"), number, source, time.monotonic_ns())
    if ticket == -errno.EAGAIN:
        raise CommandRingFull(
            f"{name}: command ring full ({lib.XRF_CMD_SLOTS} pending): "
            "the loop is not taking commands (is it still running?)"
        )
    if ticket in (-errno.EBUSY, -errno.EPROTO):
        # No slot free for its position after many tries, or a head no ticket can follow: the
        # loop wrote the ring's counters (a real loop only moves its tail).
        raise ChannelsCorrupt(f"{name}: the command ring's head and slot sequence numbers do not fit together")
    if ticket <= 0:
        raise ChannelsError(f"{name}: xrf_cmd_send failed ({ticket})")
    return int(ticket)


def wait(read_status: Callable[[], CData], name: str, ticket: int, timeout: float) -> CommandResult:
    """The outcome of command ``ticket``, once the loop has handled it (CommandTimeout if it does
    not within ``timeout`` seconds). ``read_status``: the mapping's StatusReader.read (a copy that
    may be the last good one while the loop writes the block: polled again)."""
    deadline = time.monotonic() + timeout
    slot = ticket % lib.XRF_CMD_RESULTS
    while True:
        try:
            s = read_status()
        except StatusBusy:
            s = None
        if s is not None and s.cmd_done >= ticket:
            result = int(s.cmd_results[slot])
            if result >> 1 == ticket:
                accepted = not (result & 1)
                reason = "" if accepted else c_str(s.cmd_reasons[slot])
            else:
                # More than XRF_CMD_RESULTS commands were handled since: the outcome is gone.
                accepted, reason = False, "outcome no longer known (too many commands since)"
            return CommandResult(
                ticket=ticket,
                accepted=accepted,
                state=int(s.state),
                state_name=state_name(int(s.state)),
                reason=reason,
            )
        if time.monotonic() >= deadline:
            where = "status unknown"
            if s is not None:
                st = status_from_struct(s)
                where = f"state {st.state_name}, loop {'running' if st.running else 'not running'}"
            raise CommandTimeout(f"{name}: command #{ticket} not handled within {timeout:g} s ({where})")
        time.sleep(0.001)  # polling the loop's status
