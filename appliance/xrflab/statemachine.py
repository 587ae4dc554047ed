"""FullStateMachine as data, read out of rt_core's C tables through the cffi binding.

The loop decides every transition with ``xrf_cmd_transition`` (a command in a state) and
``xrf_state_complete`` (a state's hook completing), both in ``rt_core/src/channels.c``. The
dashboard draws the machine and the appliance serves it (``GET /api/state-machine``) from this
module, which asks those two functions about every (state, command) pair: nobody else writes the
transitions down, so nothing can disagree with the loop.
"""

from __future__ import annotations

from pydantic import BaseModel, Field

from .channels import COMMAND_NUMBERS, STATE_NUMBERS, lib
from .channels.names import SAFE_COMMANDS


class Named(BaseModel):
    number: int = Field(description="the value in xrf_status.state / a command ring slot")
    name: str


class Command(Named):
    safe: bool = Field(
        description="only brings a running controller to rest (stop, pause): anyone who may stop "
        "sends it without the bench lease (channels.h's XRF_CMDS says which)"
    )


class Transition(BaseModel):
    source: str = Field(alias="from", description="state the command is sent in")
    cmd: str = Field(description="command name (POST /api/runs/current/command, the WebSocket `command`)")
    to: str = Field(description="state the loop enters when it accepts the command")

    model_config = {"populate_by_name": True}


class Completion(BaseModel):
    source: str = Field(alias="from", description="state whose hook completed (returned 1)")
    to: str

    model_config = {"populate_by_name": True}


class StateMachine(BaseModel):
    """Every state and command, and where each leads; a (state, command) pair missing from
    `transitions` is rejected by the loop as not allowed."""

    states: list[Named]
    commands: list[Command]
    transitions: list[Transition]
    completions: list[Completion]


def _name_of(numbers: dict[str, int], number: int) -> str:
    return next(name for name, n in numbers.items() if n == number)


def state_machine() -> StateMachine:
    """The machine as the C tables define it (cheap: 60 calls into C)."""
    transitions = [
        Transition(source=state, cmd=cmd, to=_name_of(STATE_NUMBERS, target))
        for state, s in STATE_NUMBERS.items()
        for cmd, c in COMMAND_NUMBERS.items()
        if (target := lib.xrf_cmd_transition(s, c)) > 0
    ]
    completions = [
        Completion(source=state, to=_name_of(STATE_NUMBERS, target))
        for state, s in STATE_NUMBERS.items()
        if (target := lib.xrf_state_complete(s)) > 0
    ]
    return StateMachine(
        states=[Named(number=n, name=name) for name, n in STATE_NUMBERS.items()],
        commands=[Command(number=n, name=name, safe=name in SAFE_COMMANDS) for name, n in COMMAND_NUMBERS.items()],
        transitions=transitions,
        completions=completions,
    )
