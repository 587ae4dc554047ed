"""Scenario files and checks, in process (docs/educators/grading.md): every mistake refused with
its line, the expression language closed, and the step-response figures right on curves whose
figures are known in closed form."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from xrflab import plants
from xrflab.grading import ScenarioError, check_signals, load
from xrflab.grading import expr as gexpr
from xrflab.grading.checks import RunData, evaluate
from xrflab.grading.project import logged_variables, ros2xeno_fields

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = REPO / "student_projects" / "scenarios"
EXAMPLES = REPO / "student_projects" / "examples"

HEAD = """[scenario]
robot = "stage"
duration = 2.0

[[commands]]
at = 0.0
cmd = "initialise"

[[commands]]
at = 0.05
cmd = "start"
"""


def refused(text: str) -> ScenarioError:
    with pytest.raises(ScenarioError) as info:
        load(text, "s.toml", tuple(plants.names()))
    return info.value


@pytest.mark.parametrize("name", ["stage", "jiwy"])
def test_the_examples_scenarios_load_and_name_only_signals_their_example_has(name: str) -> None:
    s = load((SCENARIOS / f"{name}.toml").read_text(), f"{name}.toml", tuple(plants.names()))
    project = EXAMPLES / name
    check_signals(s, ros2xeno_fields(project), logged_variables(project))
    assert s.robot == name and s.max_points > 0
    # The same scenario against another example: its signals are not there, and the line says where.
    other = EXAMPLES / ("jiwy" if name == "stage" else "stage")
    with pytest.raises(ScenarioError) as info:
        check_signals(s, ros2xeno_fields(other), logged_variables(other), f"{name}.toml")
    first = min(sp.line for sp in s.setpoints)
    assert info.value.line == first and "unknown setpoint signal" in info.value.reason


def test_a_syntax_error_is_refused_with_its_line() -> None:
    err = refused(HEAD + '\n[[checks]]\nkind = "state"\nby = 1.0\npoints = = 2\n')
    assert err.line == HEAD.count("\n") + 5
    assert "not valid TOML" in err.reason and err.detail == {"error": err.reason, "line": err.line, "file": "s.toml"}


@pytest.mark.parametrize(
    ("check", "key", "words"),
    [
        ('kind = "rise_time"\nsignal = "position"\nat = 0.2\nto = 0.05\nmax = 0', "max", "no value can meet it"),
        (
            'kind = "overshoot"\nsignal = "position"\nat = 1.5\nuntil = 1.0\nto = 0.05\nmax_percent = 5',
            "until",
            "not after the step",
        ),
        ('kind = "bound"\nsignal = "pwm"\nmin = 10\nmax = -10', "min", "no value can meet it"),
        ('kind = "bound"\nsignal = "pwm"\nduring = [1.5, 0.5]\nmax_abs = 1', "during", "an empty window"),
        ('kind = "settling_time"\nsignal = "position"\nat = 1.8\nto = 0.05\nmax = 1.0', "max", "longer than the span"),
        ('kind = "reach"\nsignal = "position"\nvalue = 1\ntolerance = 0.1\nby = 9', "by", "outside the scenario"),
        ('kind = "bound"\nsignal = "pwm"\nmax_abs = 1\nwithin = 3', "within", "unknown key"),
        ('kind = "wobble"', "kind", "unknown check kind"),
        ("kind = \"expression\"\nexpr = \"__import__('os').system('true')\"", "expr", "unknown function"),
        ('kind = "expression"\nexpr = "position.real > 0"', "expr", "not allowed"),
        ('kind = "expression"\nexpr = "open(position)"', "expr", "unknown function"),
        ('kind = "expression"\nexpr = "(position > 0"', "expr", "syntax error"),
    ],
)
def test_an_impossible_or_unknown_check_is_refused_at_the_line_of_its_key(check: str, key: str, words: str) -> None:
    text = HEAD + '\n[[checks]]\nid = "c"\n' + check + "\n"
    err = refused(text)
    lines = text.splitlines()
    want = next(n for n, line in enumerate(lines, 1) if line.startswith(f"{key} ="))
    assert err.line == want, (err.line, err.reason)
    assert words in err.reason


def test_unknown_commands_robots_and_a_missing_start_are_refused() -> None:
    assert "unknown command" in refused(HEAD.replace('"start"', '"launch"') + '[[checks]]\nkind = "no_alarms"\n').reason
    assert "unknown robot" in refused(HEAD.replace('"stage"', '"tank"') + '[[checks]]\nkind = "no_alarms"\n').reason
    err = refused(HEAD.replace('"start"', '"stop"') + '[[checks]]\nkind = "no_alarms"\n')
    assert "no 'start'" in err.reason and err.line == 5
    assert "nothing to grade" in refused(HEAD).reason


def test_an_unknown_signal_in_an_expression_is_refused_with_its_line() -> None:
    text = HEAD + '\n[[checks]]\nkind = "expression"\nexpr = "abs(positon) < 1"\n'
    s = load(text, "s.toml")
    with pytest.raises(ScenarioError) as info:
        check_signals(s, {"position_setpoint"}, {"position", "position_setpoint", "pwm"}, "s.toml")
    assert info.value.line == HEAD.count("\n") + 4 and "'positon'" in info.value.reason


def test_expressions_compute_over_arrays_and_never_run_python() -> None:
    cols = {"t": np.array([0.0, 1.0, 2.0]), "x": np.array([1.0, -2.0, 3.0])}
    assert list(gexpr.evaluate("abs(x) > 1.5", cols)) == [False, True, True]
    assert gexpr.evaluate("rms(x)", cols) == pytest.approx(math.sqrt(14 / 3))
    assert list(gexpr.evaluate("0 < t <= 1", cols)) == [False, True, False]
    assert gexpr.names("maximum(x, y) + t * pi") == {"x", "y"}
    for bad in ("x.__class__", "[x]", "lambda: 1", "'text'", "x if x else 1", "globals()", "x[0]"):
        with pytest.raises(gexpr.ExprError):
            gexpr.compile_expr(bad)
    with pytest.raises(gexpr.ExprError, match="exponent"):
        gexpr.evaluate("x ** 1000", cols)


def _step_data(tau: float, zeta: float | None, dt: float = 0.001, at: float = 0.2, to: float = 1.0) -> RunData:
    t = np.arange(0.0, 3.0, dt)
    s = np.clip(t - at, 0.0, None)
    if zeta is None:  # first order
        y = to * (1 - np.exp(-s / tau))
    else:  # second order, underdamped, natural frequency 1/tau
        wn = 1.0 / tau
        wd = wn * math.sqrt(1 - zeta**2)
        y = to * (1 - np.exp(-zeta * wn * s) * (np.cos(wd * s) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * s)))
    return RunData(
        columns={"t": t, "y": y, "sp": np.where(t >= at, to, 0.0)},
        states=[(0.0, "INITIALISED"), (0.05, "RUN")],
        reached=3.0,
    )


STEP = """[scenario]
robot = "stage"
duration = 3.0
[[commands]]
at = 0.0
cmd = "start"
[[checks]]
id = "rise"
kind = "rise_time"
signal = "y"
at = 0.2
to = 1.0
max = 1.0
[[checks]]
id = "over"
kind = "overshoot"
signal = "y"
at = 0.2
to = 1.0
max_percent = 10
[[checks]]
id = "settle"
kind = "settling_time"
signal = "y"
at = 0.2
to = 1.0
band_percent = 2
max = 2.5
[[checks]]
id = "sse"
kind = "steady_state_error"
signal = "y"
at = 0.2
to = 1.0
max = 0.01
"""


def test_step_response_figures_match_the_closed_form() -> None:
    s = load(STEP, "step.toml")
    first = {r.id: r for r in evaluate(s, _step_data(0.1, None))}
    assert first["rise"].value == pytest.approx(0.1 * math.log(9), abs=0.002)  # 10-90 %: tau ln 9
    assert first["over"].value == 0 and first["over"].passed
    assert first["settle"].value == pytest.approx(0.1 * math.log(50), abs=0.002)  # 2 % band: tau ln 50
    assert first["sse"].passed and first["sse"].value < 1e-6
    zeta = 0.3
    second = {r.id: r for r in evaluate(s, _step_data(0.1, zeta))}
    want = 100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2))  # 37.2 %
    assert second["over"].value == pytest.approx(want, rel=0.01)
    assert not second["over"].passed and second["over"].earned == 0 and "overshoot 37.2 %" in second["over"].reason
    assert second["over"].plot is not None and second["over"].plot["bounds"][0]["y"] == pytest.approx(1.1)


def test_a_run_that_ended_early_grades_what_it_got_through_and_says_why_for_the_rest() -> None:
    text = STEP + '[[checks]]\nid = "early"\nkind = "bound"\nsignal = "y"\nduring = [0.0, 0.3]\nmax_abs = 2\n'
    s = load(text, "step.toml")
    data = _step_data(0.1, None)
    keep = data.columns["t"] <= 0.5
    data.columns = {k: v[keep] for k, v in data.columns.items()}
    data.complete, data.reached, data.reason = False, 0.5, "the controller ended at t = 0.500 s (killed by SIGSEGV)"
    res = {r.id: r for r in evaluate(s, data)}
    assert res["early"].passed and res["early"].earned == 1
    for cid in ("rise", "over", "settle", "sse"):
        assert res[cid].earned == 0 and "SIGSEGV" in res[cid].reason
