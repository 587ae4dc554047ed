"""GET /api/state-machine is rt_core's command table: for every (state, command) pair the served
machine says what channels.c does when a loop handles that command (issue 20)."""

from __future__ import annotations

from xrf_testing.harness import Server
from xrf_testing.testloop import LoopSide, create_for_test


def test_served_machine_is_what_the_c_table_does(server: Server, shm_name: str) -> None:
    r = server.http.get("/api/state-machine")
    assert r.status_code == 200, r.text
    machine = r.json()
    states = {s["name"]: s["number"] for s in machine["states"]}
    commands = {c["name"]: c["number"] for c in machine["commands"]}
    assert list(states) == [
        "IDLE",
        "INITIALISING",
        "INITIALISED",
        "RUN",
        "STOPPING",
        "STOPPED",
        "PAUSING",
        "PAUSED",
        "ERROR",
        "QUIT",
    ]
    assert list(commands) == ["initialise", "start", "stop", "reset", "pause", "quit"]
    served = {(t["from"], t["cmd"]): t["to"] for t in machine["transitions"]}
    assert len(served) == len(machine["transitions"])  # one target per pair

    # Every pair through the command ring and the loop side's C table (LoopSide applies
    # xrf_cmd_transition as the loop does): accepted exactly where the served machine has an edge.
    with create_for_test(shm_name) as ch:
        loop = LoopSide(ch)
        for state, s in states.items():
            for cmd, c in commands.items():
                loop.set_state(s)
                ticket = ch.send_command(c)
                loop.handle_commands()
                result = ch.wait_command(ticket, timeout=1)
                target = served.get((state, cmd))
                assert result.accepted == (target is not None), (state, cmd, result)
                assert result.state_name == (target or state), (state, cmd, result)

    # A hook completing: every state with a hook that leads somewhere, as FullStateMachine::step
    # follows it (rt_core/tests/test_state_machine.cpp runs that).
    completions = {c["from"]: c["to"] for c in machine["completions"]}
    assert completions == {
        "INITIALISING": "INITIALISED",
        "INITIALISED": "RUN",
        "RUN": "STOPPING",
        "STOPPING": "STOPPED",
        "PAUSING": "PAUSED",
    }
    assert set(completions) | set(completions.values()) <= set(states)


def test_state_machine_needs_a_login(server: Server) -> None:
    import httpx

    with httpx.Client(base_url=server.url) as anonymous:
        assert anonymous.get("/api/state-machine").status_code == 401
