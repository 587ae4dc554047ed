"""Names of the C side's numbers: states, commands, cycle stages, host-lost actions.

channels.h lists them once (the X-macros ``XRF_STATES``, ``XRF_CMDS``: number, name, whether a
command is safe) and channels.c names them (``xrf_state_name``, ``xrf_cmd_name``, ``xrf_cmd_safe``)
and holds the one command table (``xrf_cmd_transition``); these tables are made from those at
import, so a state or command added in C appears here without an edit.
"""

from __future__ import annotations

import functools

from .binding import c_str, lib

# Stage names in the order of the XRF_STAGE_* indices; the numbers themselves come from the header.
STAGE_NAMES: tuple[str, ...] = tuple(
    sorted(
        ("wakeup", "fpga", "data", "cmd", "monitor", "hook", "logger", "cycle"),
        key=lambda name: getattr(lib, "XRF_STAGE_" + name.upper()),
    )
)

# What the loop does when the host's heartbeat goes stale, by name (channels.h's XRF_HOST_LOST_ACTIONS).
HOST_LOST_ACTIONS: dict[str, int] = {
    c_str(lib.xrf_host_lost_action_name(a)): a for a in range(lib.XRF_HOST_LOST_ACTION_COUNT)
}

# What the safety watcher does to the outputs on an exit or hang, by name (watch.h's
# XRF_SAFE_REACTIONS): a bench profile's safety.reaction.
SAFE_REACTIONS: dict[str, int] = {c_str(lib.xrf_safe_reaction_name(r)): r for r in range(lib.XRF_SAFE_REACTION_COUNT)}


# The board transports of channels.h's XRF_TRANSPORTS (XRF_TRANSPORT / xrf_info.transport values).
TRANSPORTS: tuple[str, ...] = tuple(c_str(lib.xrf_transport_name(t)) for t in range(lib.XRF_TRANSPORT_COUNT))


@functools.lru_cache(maxsize=64)  # bounded: the number comes from the loop's status block
def state_name(state: int) -> str:
    return c_str(lib.xrf_state_name(state))


def command_name(cmd: int) -> str:
    return c_str(lib.xrf_cmd_name(cmd))


# channels.c asserts the numbers are 1..count.
COMMAND_NUMBERS: dict[str, int] = {command_name(c): c for c in range(1, lib.XRF_CMD_COUNT + 1)}
STATE_NUMBERS: dict[str, int] = {state_name(s): s for s in range(1, lib.XRF_STATE_COUNT + 1)}
# Commands that only bring a controller to rest (stop, pause): anyone who may stop sends them
# without the bench lease (server/security/auth.py), the ROS bridge even without the lease gate.
SAFE_COMMANDS: frozenset[str] = frozenset(name for name, number in COMMAND_NUMBERS.items() if lib.xrf_cmd_safe(number))


def command_number(cmd: str | int) -> int:
    """A command name ("start") or number; numbers pass unchecked (the loop rejects bad ones)."""
    if isinstance(cmd, int):
        return cmd
    text = cmd.strip().lower()
    if text.lstrip("-").isdigit():
        return int(text)
    if text not in COMMAND_NUMBERS:
        raise ValueError(f"unknown command {cmd!r}; commands: {', '.join(COMMAND_NUMBERS)}")
    return COMMAND_NUMBERS[text]


def allowed_commands(state: int) -> list[str]:
    """Names of the commands the loop accepts in `state`, from the one command table in C."""
    return [name for name, number in COMMAND_NUMBERS.items() if lib.xrf_cmd_transition(state, number) > 0]
