"""What can go wrong between a host and a loop's segment, as exceptions callers catch by kind.

In a module of their own because every other module of the package raises them and callers
(the CLI, the supervisor, the ROS 2 bridge) catch ``ChannelsError`` without caring which part of
the package raised it.
"""

from __future__ import annotations


class ChannelsError(RuntimeError):
    """The shared memory is missing, foreign, or a channel refused an operation."""


class ChannelsCorrupt(ChannelsError):
    """The loop broke the rules of its segment: a ring's geometry, a head or tail, a log layout,
    a schema is not one the runtime writes. Everything in the segment is the loop's (a student's
    program) to write: a reader that sees this stops trusting the segment, and the appliance
    stops the run (alarm and end reason ``corrupt_channel``). The message says what was wrong."""


class StatusBusy(ChannelsError):
    """The status block is being written and no earlier copy of it was read yet: ask again (a
    reader that had one gets that instead, channels/status.py)."""


class CommandRingFull(ChannelsError):
    """The loop is not taking commands (stopped cycling, or far behind)."""


class CommandTimeout(ChannelsError, TimeoutError):
    """A command was queued but the loop did not handle it in time."""
