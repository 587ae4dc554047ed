"""Host side of a loop process's shared memory (``/dev/shm/<name>``), through cffi.

The layout and every ring operation come from rt_core's channels.h/channels.c (``_cffi_build``
compiles them into one binding, ``binding``); this package only adds Python types around them.
One ``Channels`` object maps one run's segment. A module per job:

- ``binding``: the compiled cffi module (``ffi``, ``lib``), loaded once;
- ``names``: states, commands, cycle stages and host-lost actions by name, from the C tables;
- ``errors``: ``ChannelsError`` and its kinds;
- ``segment``: where a segment is, mapping and checking it, whose it is (replaced, removal);
- ``status``: the status block as ``Status`` and the stages' ``Histogram``;
- ``commands``: a command in, its ``CommandResult`` out;
- ``rings``: telemetry and monitor readers, each with its own cursor;
- ``host``: ``Channels``, the object callers hold, over the modules above.

The loop's part played from Python (``create_for_test``, ``LoopSide``) is test scaffolding and lives
with the tests, in ``tests/xrf_testing/testloop.py``.

Callers import from the package (``from xrflab.channels import Channels``); the names below are
its public face.
"""

from __future__ import annotations

from .binding import ffi, lib
from .commands import CommandResult
from .errors import ChannelsCorrupt, ChannelsError, CommandRingFull, CommandTimeout, StatusBusy
from .host import Channels
from .names import (
    COMMAND_NUMBERS,
    HOST_LOST_ACTIONS,
    SAFE_REACTIONS,
    STAGE_NAMES,
    STATE_NUMBERS,
    allowed_commands,
    command_name,
    command_number,
    state_name,
)
from .rings import MonitorLine, MonitorReader, Telemetry, TelemetryReader
from .segment import SHM_DIR, SHM_SIZE, remove_if_owned, shm_path
from .status import Histogram, Status

__all__ = [
    "COMMAND_NUMBERS",
    "HOST_LOST_ACTIONS",
    "SAFE_REACTIONS",
    "SHM_DIR",
    "SHM_SIZE",
    "STAGE_NAMES",
    "STATE_NUMBERS",
    "Channels",
    "ChannelsCorrupt",
    "ChannelsError",
    "CommandResult",
    "CommandRingFull",
    "CommandTimeout",
    "Histogram",
    "MonitorLine",
    "MonitorReader",
    "Status",
    "StatusBusy",
    "Telemetry",
    "TelemetryReader",
    "allowed_commands",
    "command_name",
    "command_number",
    "ffi",
    "lib",
    "remove_if_owned",
    "shm_path",
    "state_name",
]
