"""xrflab/statemachine.py in-process: the machine read out of channels.c's tables, as the appliance
serves it (tests/server/test_state_machine_api.py checks the served copy against a loop side)."""

from __future__ import annotations

from xrflab.channels import COMMAND_NUMBERS, STATE_NUMBERS, allowed_commands
from xrflab.statemachine import state_machine


def test_every_state_and_command_once_with_its_c_number() -> None:
    m = state_machine()
    assert {s.name: s.number for s in m.states} == STATE_NUMBERS
    assert {c.name: c.number for c in m.commands} == COMMAND_NUMBERS
    assert len({s.number for s in m.states}) == len(m.states)
    assert [s.name for s in m.states][:4] == ["IDLE", "INITIALISING", "INITIALISED", "RUN"]


def test_the_normal_path_and_what_is_refused() -> None:
    edges = {(t.source, t.cmd): t.to for t in state_machine().transitions}
    assert len(edges) == len(state_machine().transitions)  # one target per (state, command)
    # a run's life as the dashboard drives it
    assert edges[("IDLE", "initialise")] == "INITIALISING"
    assert edges[("INITIALISED", "start")] == "RUN"
    assert edges[("RUN", "stop")] == "STOPPING"
    assert edges[("RUN", "pause")] == "PAUSING"
    # not allowed: starting what was never initialised, stopping what is idle
    assert ("IDLE", "start") not in edges
    assert ("IDLE", "stop") not in edges
    # the machine and allowed_commands (what the WebSocket status offers) agree for every state
    for state, number in STATE_NUMBERS.items():
        assert sorted(allowed_commands(number)) == sorted(c for (s, c) in edges if s == state), state


def test_completions_lead_forward_and_the_wire_names_are_from_and_to() -> None:
    m = state_machine()
    completions = {c.source: c.to for c in m.completions}
    assert completions["INITIALISING"] == "INITIALISED"
    assert completions["STOPPING"] == "STOPPED"
    assert "IDLE" not in completions and "QUIT" not in completions
    wire = m.model_dump(by_alias=True)
    assert set(wire["transitions"][0]) == {"from", "cmd", "to"}
    assert set(wire["completions"][0]) == {"from", "to"}
