"""`xrf grade SCENARIO PROJECT_DIR`: a scenario run on a project here, as the appliance runs it
(a TA's laptop, a course's CI). Prints each check and the total; exit 0 when every check passed,
4 when some failed, 5 when the build or run failed (crash, hang, never in RUN), 1 for a bad
scenario (with its line), 2 for usage. docs/educators/grading.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

HELP = "grade a project with a scenario (build, run on the simulated robot, check its log)"
EXIT_PASSED, EXIT_ERROR, EXIT_FAILED_CHECKS, EXIT_RUN_FAILED = 0, 1, 4, 5


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", type=Path, help="the scenario file (TOML)")
    p.add_argument("project", type=Path, help="the project folder (or an executable with --exe)")
    p.add_argument("--exe", action="store_true", help="PROJECT is an already built controller executable")
    p.add_argument(
        "--work", type=Path, help="keep the build, the run's log and output here (default: a temporary folder)"
    )
    p.add_argument("--json", action="store_true", help="the result as one JSON object on stdout")
    p.add_argument(
        "--virtual-time", action="store_true", default=None, help="run the loop on simulated time (XRF_VIRTUAL_TIME=1)"
    )


def run(args: argparse.Namespace) -> int:
    from . import project as proj
    from .runner import grade_executable, grade_project
    from .scenario import ScenarioError, check_signals, load

    try:
        text = args.scenario.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        print(f"xrf grade: {args.scenario}: cannot read it: {exc}", file=sys.stderr)
        return EXIT_ERROR
    try:
        from .. import plants

        scenario = load(text, str(args.scenario), tuple(plants.names()))
        if not args.exe:
            check_signals(
                scenario, proj.ros2xeno_fields(args.project), proj.logged_variables(args.project), str(args.scenario)
            )
    except ScenarioError as exc:
        print(f"xrf grade: {exc}", file=sys.stderr)
        return EXIT_ERROR
    say = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    with tempfile.TemporaryDirectory(prefix="xrf-grade-") as tmp:
        work = args.work or Path(tmp)
        if args.exe:
            result = grade_executable(scenario, args.project.resolve(), work / "run", virtual_time=args.virtual_time)
        else:
            result = grade_project(scenario, args.project, work, virtual_time=args.virtual_time, log=lambda _l: None)
    if args.json:
        print(json.dumps(result.as_dict(plots=False)))
    else:
        say(f"{scenario.name}: {result.status}" + (f" ({result.reason})" if result.reason else ""))
        for c in result.checks:
            mark = "PASS" if c.passed else "FAIL"
            value = "" if c.value is None else f" = {c.value:.4g}"
            say(f"  {mark} {c.id} [{c.earned:g}/{c.points:g}] {c.kind}{value} ({c.limit})")
            if not c.passed:
                say(f"       {c.reason}" + (f" -- {c.message}" if c.message else ""))
        if result.status != "completed" and result.output_tail:
            say("  the controller's last output:")
            for line in result.output_tail[-5:]:
                say(f"    {line}")
        say(f"total: {result.earned:g} / {result.points:g} points ({result.wall_s:.1f} s)")
    if result.status != "completed":
        return EXIT_RUN_FAILED
    return EXIT_PASSED if all(c.passed for c in result.checks) else EXIT_FAILED_CHECKS
