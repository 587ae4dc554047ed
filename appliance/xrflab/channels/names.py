"""Names of the C side's numbers: states, commands, cycle stages, host-lost actions.

channels.h numbers them and channels.c names them (``xrf_state_name``, ``xrf_cmd_name``) and holds
the one command table (``xrf_cmd_transition``); these tables are made from those at import, so a
state or command added in C appears here without an edit.
"""

from __future__ import annotations

from .binding import c_str, lib

# Stage names in the order of the XRF_STAGE_* indices; the numbers themselves come from the header.
STAGE_NAMES: tuple[str, ...] = tuple(
    sorted(
        ("wakeup", "fpga", "data", "cmd", "monitor", "hook", "logger", "cycle"),
        key=lambda name: getattr(lib, "XRF_STAGE_" + name.upper()),
    )
)

HOST_LOST_ACTIONS = {
    "ignore": lib.XRF_HOST_LOST_IGNORE,
    "pause": lib.XRF_HOST_LOST_PAUSE,
    "stop": lib.XRF_HOST_LOST_STOP,
}


def state_name(state: int) -> str:
    return c_str(lib.xrf_state_name(state))


def command_name(cmd: int) -> str:
    return c_str(lib.xrf_cmd_name(cmd))


COMMAND_NUMBERS: dict[str, int] = {command_name(c): c for c in range(lib.XRF_CMD_INITIALISE, lib.XRF_CMD_QUIT + 1)}
STATE_NUMBERS: dict[str, int] = {state_name(s): s for s in range(lib.XRF_STATE_IDLE, lib.XRF_STATE_QUIT + 1)}


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
