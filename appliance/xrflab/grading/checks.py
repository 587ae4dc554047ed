"""Evaluating a scenario's checks on what a run left: its log's columns and what the runner saw.

Time is loop time: the log's `cycle` column over the cycle frequency, the same clock the runner
sent commands and setpoints by, so a check means the same in real and in simulated time.
A run that ended early (crash, hang) grades the checks whose window it got through and gives
0 points, with the run's reason, to the rest (docs/educators/grading.md, "When a build fails").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import expr
from .results import PLOT_POINTS, CheckResult
from .scenario import Check, Scenario


@dataclass
class RunData:
    columns: dict[str, np.ndarray]  # the log's columns as float arrays, and "t" (s of loop time)
    states: list[tuple[float, str]] = field(default_factory=list)  # (loop time, state) as seen
    missed: int = 0
    alarms: list[str] = field(default_factory=list)
    reached: float = 0.0  # loop time the run got to
    complete: bool = True
    reason: str = ""  # why not complete


def evaluate(scenario: Scenario, data: RunData) -> list[CheckResult]:
    return [evaluate_one(c, scenario, data) for c in scenario.checks]


def evaluate_one(check: Check, scenario: Scenario, data: RunData) -> CheckResult:
    res = CheckResult(check.id, check.kind, check.points, 0.0, False, message=check.message, line=check.line)
    t1, t2 = check.window(scenario.duration)
    early = not data.complete and (t2 > data.reached + 1e-9 or check.kind in ("no_deadline_misses", "no_alarms"))
    # "By a time" checks met before the run ended early are met: later samples cannot undo them.
    if not early or check.kind in ("state", "reach"):
        try:
            _KINDS[check.kind](check, data, res, t1, t2)
        except (expr.ExprError, _NoData) as exc:
            res.passed = False
            res.reason = str(exc)
    if early and not res.passed:
        res.plot = None
        res.reason = (
            f"not evaluated: {data.reason or 'the run ended early'} (at t = {data.reached:.3f} s, before {t2:g} s)"
        )
        return res
    if res.passed:
        res.earned = check.points
        res.reason = ""
    return res


class _NoData(Exception):
    pass


def _signal(check: Check, data: RunData, t1: float, t2: float) -> tuple[np.ndarray, np.ndarray]:
    if check.signal not in data.columns:
        have = ", ".join(sorted(k for k in data.columns if k != "t")) or "none"
        raise _NoData(f"the log has no signal {check.signal!r} (it has: {have})")
    t = data.columns["t"]
    mask = (t >= t1) & (t <= t2)
    if not mask.any():
        raise _NoData(f"no samples of {check.signal!r} between {t1:g} and {t2:g} s (the controller logs only in RUN)")
    return t[mask], data.columns[check.signal][mask]


def _plot(
    check: Check, t: np.ndarray, y: np.ndarray, t1: float, t2: float, bounds: list[dict[str, object]]
) -> dict[str, object]:
    step = max(1, len(t) // PLOT_POINTS)
    return {
        "signal": check.signal or check.id,
        "t": [round(float(x), 6) for x in t[::step]],
        "y": [float(x) for x in y[::step]],
        "window": [t1, t2],
        "bounds": bounds,
    }


def _step(check: Check, data: RunData, t1: float, t2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """The response after the step as a fraction of the way from `from` to `to`."""
    t, y = _signal(check, data, t1, t2)
    p = check.params
    if "from" in p:
        start = float(p["from"])
    else:
        allt, ally = data.columns["t"], data.columns[check.signal]
        before = ally[allt < t1]
        start = float(before[-1]) if len(before) else float(y[0])
    to = float(p["to"])
    if abs(to - start) < 1e-12:
        raise _NoData(f"no step: {check.signal} already at {to:g} before {t1:g} s (give 'from')")
    return t, y, (y - start) / (to - start), start, to


def _rise_time(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    t, y, frac, start, to = _step(check, data, t1, t2)
    res.limit = f"<= {check.params['max']:g} s"
    lo, hi = start + 0.1 * (to - start), start + 0.9 * (to - start)
    res.plot = _plot(check, t, y, t1, t2, [{"y": lo, "label": "10 %"}, {"y": hi, "label": "90 %"}])
    i10, i90 = np.flatnonzero(frac >= 0.1), np.flatnonzero(frac >= 0.9)
    if not len(i90):
        res.reason = f"{check.signal} never got to 90 % of the step (to {hi:g}) by {t2:g} s"
        return
    res.value = float(t[i90[0]] - t[i10[0]])
    res.passed = res.value <= check.params["max"]
    res.reason = f"rise time {res.value:.3f} s > {check.params['max']:g} s"


def _overshoot(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    t, y, frac, start, to = _step(check, data, t1, t2)
    limit = check.params["max_percent"]
    res.limit = f"<= {limit:g} %"
    res.value = float(max(0.0, float(frac.max()) - 1.0) * 100.0)
    res.plot = _plot(
        check,
        t,
        y,
        t1,
        t2,
        [{"y": to + (to - start) * limit / 100, "label": f"+{limit:g} %"}, {"y": to, "label": "target"}],
    )
    res.passed = res.value <= limit
    res.reason = f"overshoot {res.value:.1f} % > {limit:g} %"


def _settling_time(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    t, y, frac, start, to = _step(check, data, t1, t2)
    band = check.params["band_percent"] / 100
    res.limit = f"<= {check.params['max']:g} s (±{check.params['band_percent']:g} %)"
    d = abs(to - start) * band
    res.plot = _plot(check, t, y, t1, t2, [{"y": to + d, "label": "band"}, {"y": to - d, "label": "band"}])
    outside = np.flatnonzero(np.abs(frac - 1.0) > band)
    if len(outside) and outside[-1] == len(t) - 1:
        res.reason = f"{check.signal} had not settled within ±{check.params['band_percent']:g} % by {t2:g} s"
        return
    res.value = float(t[outside[-1] + 1] - t1) if len(outside) else float(t[0] - t1)
    res.passed = res.value <= check.params["max"]
    res.reason = f"settling time {res.value:.3f} s > {check.params['max']:g} s"


def _steady_state_error(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    t, y, _frac, _start, to = _step(check, data, t1, t2)
    tail = t >= t2 - check.params["window"]
    res.limit = f"<= {check.params['max']:g}"
    res.value = float(abs(float(np.mean(y[tail])) - to))
    m = check.params["max"]
    res.plot = _plot(
        check, t, y, t1, t2, [{"y": to + m, "label": "error bound"}, {"y": to - m, "label": "error bound"}]
    )
    res.passed = res.value <= m
    res.reason = f"steady-state error {res.value:.4g} > {m:g}"


def _bound(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    t, y = _signal(check, data, t1, t2)
    p = check.params
    bad = np.zeros(len(y), dtype=bool)
    bounds: list[dict[str, object]] = []
    limits = []
    if "max_abs" in p:
        bad |= np.abs(y) > p["max_abs"]
        bounds += [{"y": p["max_abs"], "label": "|x| max"}, {"y": -p["max_abs"], "label": "|x| max"}]
        limits.append(f"|{check.signal}| <= {p['max_abs']:g}")
    if "min" in p:
        bad |= y < p["min"]
        bounds.append({"y": p["min"], "label": "min"})
        limits.append(f">= {p['min']:g}")
    if "max" in p:
        bad |= y > p["max"]
        bounds.append({"y": p["max"], "label": "max"})
        limits.append(f"<= {p['max']:g}")
    res.limit = ", ".join(limits) + f" during [{t1:g}, {t2:g}] s"
    res.value = float(np.max(np.abs(y))) if "max_abs" in p else float(y[np.argmax(bad)] if bad.any() else y[-1])
    res.plot = _plot(check, t, y, t1, t2, bounds)
    res.passed = not bad.any()
    if bad.any():
        i = int(np.argmax(bad))
        res.reason = f"{check.signal} = {float(y[i]):.4g} at t = {float(t[i]):.3f} s is out of bounds ({res.limit})"


def _reach(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    p = check.params
    t, y = _signal(check, data, 0.0, float(data.columns["t"][-1]) if len(data.columns["t"]) else t2)
    res.limit = f"|{check.signal} - {p['value']:g}| <= {p['tolerance']:g} by {p['by']:g} s"
    res.plot = _plot(
        check,
        t,
        y,
        0.0,
        t2,
        [
            {"y": p["value"] + p["tolerance"], "label": "tolerance"},
            {"y": p["value"] - p["tolerance"], "label": "tolerance"},
            {"t": p["by"], "label": "by"},
        ],
    )
    hit = np.flatnonzero(np.abs(y - p["value"]) <= p["tolerance"])
    if not len(hit):
        res.reason = f"{check.signal} never came within {p['tolerance']:g} of {p['value']:g}"
        return
    res.value = float(t[hit[0]])
    res.passed = res.value <= p["by"]
    res.reason = f"{check.signal} got there at t = {res.value:.3f} s, after {p['by']:g} s"


def _state(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    want, by = check.params["state"], check.params["by"]
    res.limit = f"{want} by {by:g} s"
    when = next((t for t, s in data.states if s == want), None)
    if when is None:
        seen = " -> ".join(dict.fromkeys(s for _, s in data.states)) or "no state"
        res.reason = f"never in {want} (seen: {seen})"
        return
    res.value = when
    res.passed = when <= by
    res.reason = f"in {want} at t = {when:.3f} s, after {by:g} s"


def _no_deadline_misses(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    res.limit = "0 missed deadlines"
    res.value = float(data.missed)
    res.passed = data.missed == 0
    res.reason = f"{data.missed} missed deadline(s)"


def _no_alarms(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    res.limit = "no alarm"
    res.value = float(len(data.alarms))
    res.passed = not data.alarms
    res.reason = "; ".join(data.alarms[:5])


def _expression(check: Check, data: RunData, res: CheckResult, t1: float, t2: float) -> None:
    source, require = check.params["expr"], check.params["require"]
    t = data.columns["t"]
    mask = (t >= t1) & (t <= t2)
    if not mask.any():
        raise _NoData(f"no samples between {t1:g} and {t2:g} s")
    cols = {k: v[mask] for k, v in data.columns.items()}
    out = np.asarray(expr.evaluate(source, cols))
    res.limit = f"{source} ({require}, during [{t1:g}, {t2:g}] s)"
    if out.ndim == 0:
        ok = bool(out)
        res.value = float(out)
    else:
        truth = out.astype(bool)
        ok = bool(truth.all() if require == "always" else truth.any() if require == "sometime" else truth[-1])
        res.value = float(truth.mean())
        res.plot = _plot(check, cols["t"], out.astype(float), t1, t2, [])
        if not ok and require == "always":
            i = int(np.argmin(truth))
            res.reason = f"false at t = {float(cols['t'][i]):.3f} s"
    res.passed = ok
    if not ok and not res.reason:
        res.reason = f"{source}: false ({require})"


_KINDS = {
    "rise_time": _rise_time,
    "overshoot": _overshoot,
    "settling_time": _settling_time,
    "steady_state_error": _steady_state_error,
    "bound": _bound,
    "reach": _reach,
    "state": _state,
    "no_deadline_misses": _no_deadline_misses,
    "no_alarms": _no_alarms,
    "expression": _expression,
}
