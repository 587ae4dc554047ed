#!/usr/bin/env python3
"""Grading N projects: total and per-project time (issue 32's benchmark; README.md beside this).

    .venv/bin/python bench/grading/bench_grading.py [--projects 40] [--parallel 2] [--virtual-time]

The builds are the examples' (Stage, Jiwy) and a Jiwy with a bad pan gain, built once into
.cache/bench-grading/ (later runs only re-check them); the N "projects" cycle through them, so the
figures are the grading's (start, run, log, checks), not the compiler's. Each is graded with its
example's scenario (student_projects/scenarios/) through the same queue the appliance uses
(GradeQueue, `--parallel` at once) and the local launcher of `xrf grade`. Prints one line per
project (status, points, wall seconds) and the totals.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "appliance"))

from xrflab import build, plants  # noqa: E402
from xrflab.grading import GradeQueue, grade_executable, load  # noqa: E402

CACHE = REPO / ".cache" / "bench-grading"


def _built(name: str, src: Path) -> Path:
    return Path(build.build_project(src, CACHE / name / "build", log=lambda _l: None).executable)


def builds() -> dict[str, tuple[Path, str]]:
    ex = REPO / "student_projects" / "examples"
    bad = CACHE / "jiwy-bad-src"
    shutil.copytree(ex / "jiwy", bad, dirs_exist_ok=True, ignore=shutil.ignore_patterns("build"))
    cpp = bad / "src" / "JiwyController.cpp"
    text = cpp.read_text()
    line = next(x for x in text.splitlines() if x.startswith("constexpr double pan_kp"))
    cpp.write_text(text.replace(line, "constexpr double pan_kp = 100000.0, pan_ki = 1000.0, pan_kd = 0.0;"))
    return {
        "stage": (_built("stage", ex / "stage"), "stage"),
        "jiwy": (_built("jiwy", ex / "jiwy"), "jiwy"),
        "jiwy-bad-gain": (_built("jiwy-bad", bad), "jiwy"),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--projects", type=int, default=40)
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--virtual-time", action="store_true")
    args = ap.parse_args()
    t0 = time.monotonic()
    exes = builds()
    print(f"builds ready in {time.monotonic() - t0:.1f} s: {', '.join(exes)}", flush=True)
    scenarios = {
        n: load((REPO / "student_projects" / "scenarios" / f"{n}.toml").read_text(), n, tuple(plants.names()))
        for n in ("stage", "jiwy")
    }
    names = list(exes)
    with tempfile.TemporaryDirectory(prefix="xrf-bench-grading-") as tmp:
        q = GradeQueue(args.parallel)
        start = time.monotonic()
        for i in range(args.projects):
            kind = names[i % len(names)]
            exe, sc = exes[kind]
            run_dir = Path(tmp) / f"p{i:03d}"
            q.submit(
                f"{i:03d}-{kind}",
                lambda exe=exe, sc=sc, d=run_dir: grade_executable(
                    scenarios[sc], exe, d, virtual_time=args.virtual_time
                ),
            )
        q.wait()
        total = time.monotonic() - start
        q.close()
    walls, loop_s = [], 0.0
    for key, job in sorted(q.jobs.items()):
        r = job.result
        assert r is not None
        walls.append(r.wall_s)
        loop_s += r.loop_time_s
        print(
            f"{key:<20} {r.status:<10} {r.earned:>4g}/{r.points:<4g} {r.wall_s:6.2f} s  (loop time {r.loop_time_s:.2f} s, missed {r.missed})"
        )
    print(
        f"\n{args.projects} projects, {args.parallel} at once{' (virtual time)' if args.virtual_time else ''}: "
        f"total {total:.1f} s wall, {total / args.projects:.2f} s per project; "
        f"per project wall median {statistics.median(walls):.2f} s, max {max(walls):.2f} s; "
        f"scenario loop time {loop_s:.1f} s in all"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
