"""Every lock-free handoff of the channels under ThreadSanitizer (issue 30, item 6): rt_core's
two-thread stress test (rt_core/tests/test_rings_stress.c: broadcast and SPSC rings, the command
queue, the Ros2Xeno buffer, the status seqlock, the doorbell) built with -fsanitize=thread and
channels.c exactly as the loop and the cffi binding compile it. x86 hides a missing barrier at
run time; TSan does not: it checks the happens-before the C11 orderings promise, not what this CPU
happened to do. The one suppression (rt_core/tests/tsan.supp) is the seqlock payload.

And TSan must see a missing release: a copy of channels.c whose SPSC commit publishes the head
RELAXED has to fail."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
RT = REPO / "rt_core"
SUPPRESSIONS = RT / "tests/tsan.supp"
# -O1: what TSan's documentation advises (fast enough, stacks still readable).
# -Wno-string-plus-int: logformat.c skips a separator with `"text" + (i == 0)`, on purpose.
FLAGS = ["-O1", "-g", "-fsanitize=thread", "-Wall", "-Wextra", "-Werror", "-Wno-string-plus-int"]


def build(tmp: Path, channels: Path) -> Path:
    exe = tmp / "test_rings_stress_tsan"
    # rt_core/src for channels.c's private headers (hist_inline.h) when the file is a planted copy
    cmd = ["clang", *FLAGS, "-I", str(RT / "include"), "-I", str(RT / "src")]
    cmd += [str(RT / "tests/test_rings_stress.c"), str(channels)]
    cmd += [str(RT / "src/logformat.c"), "-o", str(exe), "-lpthread"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return exe


def run(exe: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, TSAN_OPTIONS=f"halt_on_error=1 exitcode=66 suppressions={SUPPRESSIONS}")
    return subprocess.run([str(exe)], capture_output=True, text=True, timeout=600, env=env)


def test_every_handoff_is_race_free_under_tsan(tmp_path: Path) -> None:
    r = run(build(tmp_path, RT / "src/channels.c"))
    assert "ThreadSanitizer" not in r.stderr, r.stderr[-6000:]
    assert r.returncode == 0 and re.search(r"\b[1-9]\d* passed, 0 failed", r.stdout), r.stdout + r.stderr[-3000:]
    for handoff in ("broadcast:", "spsc (producer waits):", "commands:", "ros2xeno/status:", "doorbell:"):
        assert handoff in r.stdout, r.stdout


def test_tsan_sees_a_missing_release(tmp_path: Path) -> None:
    # The producer's side lives in channels_inline.h (channels.c includes it with quotes, so a
    # planted copy next to a copy of channels.c is the one compiled).
    source = (RT / "src/channels_inline.h").read_text()
    publish = "XRF_STORE_REL(&r->head, XRF_LOAD_RLX(&r->head) + 1);"  # xrf_spsc_commit_inline
    assert source.count(publish) == 1
    (tmp_path / "channels_inline.h").write_text(
        source.replace(publish, "XRF_STORE_RLX(&r->head, XRF_LOAD_RLX(&r->head) + 1);")
    )
    planted = tmp_path / "channels.c"
    planted.write_text((RT / "src/channels.c").read_text())
    r = run(build(tmp_path, planted))
    assert r.returncode == 66, r.stdout + r.stderr[-3000:]
    assert "WARNING: ThreadSanitizer: data race" in r.stderr and "test_spsc" in r.stderr, r.stderr[-3000:]
