"""The arm64 tier (issue 30): rt_core, its unit tests and every student project built for aarch64
by `.ci/arm64` (Debian's cross compiler, the unit tests under qemu-aarch64) -- and the tier
failing when a copy of the tree carries an aarch64-only warning or an aarch64-only test failure,
which the x86 build and tests of the rest of the suite cannot see."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TIER = REPO / ".ci/arm64"

# A static variable nobody uses: -Wunused-variable, hence an error under XRF_WERROR -- but only
# where __aarch64__ is defined.
PLANTED_WARNING = """
#if defined(__aarch64__)
static int xrf_planted_aarch64_only;
#endif
"""
# A unit test that fails on aarch64 only (CTest picks up every rt_core/tests/test_*.c).
PLANTED_TEST = """#include <stdio.h>
int main(void)
{
#if defined(__aarch64__)
    puts("0 passed, 1 failed (planted: aarch64 only)");
    return 1;
#else
    puts("1 passed, 0 failed");
    return 0;
#endif
}
"""


def run_tier(src: Path, work: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(TIER), str(src), str(work)], capture_output=True, text=True, timeout=1800)


def copy_tree(dst: Path) -> Path:
    """What the tier reads: rt_core, the student projects and the message generator rt_core installs."""
    for part in ("rt_core", "student_projects"):
        shutil.copytree(REPO / part, dst / part)
    (dst / "appliance/xrflab").mkdir(parents=True)
    shutil.copy2(REPO / "appliance/xrflab/msgdef.py", dst / "appliance/xrflab/msgdef.py")
    return dst


def test_arm64_tier_passes(tmp_path: Path) -> None:
    r = run_tier(REPO, tmp_path / "work")
    assert r.returncode == 0, r.stderr[-6000:]
    # every example and template (a folder with a CMakeLists.txt), as the tier finds them
    projects = [d for d in (REPO / "student_projects").glob("*/*") if (d / "CMakeLists.txt").is_file()]
    assert len(projects) >= 7, projects  # relbot, jiwy, stage, cell examples; base, 20-sim, cell templates at least
    assert f"passed: rt_core, its unit tests under qemu-aarch64 and {len(projects)} student projects" in r.stderr, (
        r.stderr
    )
    # the step times, for the docs (docs/developers/testing.md, the arm64 tier)
    print(r.stderr)


def test_arm64_tier_fails_on_aarch64_only_warning(tmp_path: Path) -> None:
    src = copy_tree(tmp_path / "src")
    channels = src / "rt_core/src/channels.c"
    channels.write_text(channels.read_text() + PLANTED_WARNING)
    # x86's compiler, with the flags rt_core's -Werror build uses, accepts the planted file...
    native = subprocess.run(
        [
            "cc",
            "-std=c11",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-fsyntax-only",
            "-I",
            str(src / "rt_core/include"),
            str(channels),
        ],
        capture_output=True,
        text=True,
    )
    assert native.returncode == 0, native.stderr
    # ...the arm64 tier does not.
    r = run_tier(src, tmp_path / "work")
    assert r.returncode != 0, r.stderr[-3000:]
    assert "FAILED at 'rt_core: build (-Werror)'" in r.stderr, r.stderr[-3000:]
    assert "xrf_planted_aarch64_only" in r.stderr and "-Werror" in r.stderr, r.stderr[-3000:]


def test_arm64_tier_fails_on_aarch64_only_test_failure(tmp_path: Path) -> None:
    src = copy_tree(tmp_path / "src")
    (src / "rt_core/tests/test_planted_arm64.c").write_text(PLANTED_TEST)
    r = run_tier(src, tmp_path / "work")
    assert r.returncode != 0, r.stderr[-3000:]
    assert "FAILED at 'rt_core: unit tests (qemu)'" in r.stderr, r.stderr[-3000:]
    assert "planted: aarch64 only" in r.stderr, r.stderr[-3000:]
