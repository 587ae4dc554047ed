"""The grading runner's hold in simulated time (grading/runner.py, _next_stop): an event that fell
due while the loop ran on to its hold between the host's two looks holds it there, so the next look
acts on it on that cycle; before, the loop ran on to the event after (a jiwy scenario's start due at
cycle 50 sent at 200, its step due at 200 written at 2274: pan settling 2.2 s against 0.13 s)."""

from __future__ import annotations

from xrflab.grading import load
from xrflab.grading.runner import _next_stop

SCENARIO = """
[scenario]
name = "holds"
robot = "stage"
duration = 2.0

[[commands]]
at = 0.0
cmd = "initialise"

[[commands]]
at = 0.05
cmd = "start"

[[setpoints]]
signal = "position_setpoint"
kind = "step"
at = 0.2
value = 0.05

[[setpoints]]
signal = "position_setpoint"
kind = "ramp"
at = 1.0
end = 1.1
from = 0.05
to = 0.0

[[checks]]
id = "runs"
kind = "state"
state = "RUN"
by = 0.5
points = 1
"""


def test_an_event_due_between_two_looks_holds_the_loop_where_it_is() -> None:
    s = load(SCENARIO, "holds.toml")
    start = [c for c in s.commands if c.cmd == "start"]
    # The host looked at 49 (start not due), the loop reached its hold at 50: stay at 50.
    assert _next_stop(s, start, 50, 1000.0, acted=49) == 50
    assert _next_stop(s, start, 50, 1000.0) == 200  # the old answer: start passed, on to the step
    # Acted on at 50 (start sent; the command took a cycle): on to the step.
    assert _next_stop(s, [], 51, 1000.0, acted=50) == 200
    # The step due at 200, seen at 199, the loop at 200: stay.
    assert _next_stop(s, [], 200, 1000.0, acted=199) == 200
    assert _next_stop(s, [], 200, 1000.0, acted=200) == 1000
    # Inside a ramp every cycle is an event: a look that fell behind holds at once.
    assert _next_stop(s, [], 1050, 1000.0, acted=1040) == 1050
    assert _next_stop(s, [], 1050, 1000.0, acted=1050) == 1051
