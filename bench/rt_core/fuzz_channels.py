#!/usr/bin/env python3
"""The long run of the channels.c fuzz harness (rt_core/fuzz/fuzz_channels.c, issue 26), and its
figures: executions, exec/s, libFuzzer's coverage (cov: edges, ft: features, corpus), and the lines
of the host-side functions the corpus reaches (llvm-cov over a coverage build replaying it).

    python3 bench/rt_core/fuzz_channels.py                  # 1 h, corpus kept in /tmp/xrf_bench/fuzz_channels
    python3 bench/rt_core/fuzz_channels.py --seconds 600 --fresh

The test suite runs the same harness for 30 s (tests/rt_core/test_fuzz_channels.py). Here the corpus
grows across runs (in --work, outside the repo; --fresh starts from the repo's seeds alone), the
libFuzzer seed is random (printed), and a finding stops the run: its reproducer is kept in
<work>/artifacts and printed with the command that replays it. Exit status 0: nothing found.
Needs clang, libclang-rt-14-dev (./lab installs both) and llvm (llvm-cov, llvm-profdata).
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SEEDS = REPO / "rt_core/fuzz/corpus/channels"
# The functions a host calls on a guest's segment (channels.h's reading part, logformat.h's header).
HOST_FUNCTIONS = (
    "xrf_shm_check",
    "xrf_ring_geom_check",
    "xrf_status_read",
    "xrf_cmd_send",
    "xrf_data_in_write",
    "xrf_bcast_read_g",
    "xrf_log_meta_check",
    "xrf_spsc_peek_run_g",
    "xrf_spsc_release_g",
    "xrf_doorbell_wait",
    "xrf_logfile_header",
)


def build(build_dir: Path, coverage: bool) -> Path:
    env = dict(os.environ, CC="clang", CXX="clang++")
    options = ["-DXRF_FUZZ=ON", f"-DXRF_FUZZ_COVERAGE={'ON' if coverage else 'OFF'}"]
    subprocess.run(
        ["cmake", "-S", str(REPO / "rt_core"), "-B", str(build_dir), *options],
        env=env,
        check=True,
        stdout=subprocess.DEVNULL,
    )
    subprocess.run(
        ["cmake", "--build", str(build_dir), "--target", "fuzz_channels", "-j2"], check=True, stdout=subprocess.DEVNULL
    )
    return build_dir / "fuzz_channels"


def llvm_tool(name: str) -> str:
    """llvm-cov / llvm-profdata of clang's own version (a profile's format follows the compiler)."""
    out = subprocess.run(["clang", "--version"], capture_output=True, text=True).stdout
    m = re.search(r"version (\d+)", out)
    for candidate in ([f"{name}-{m.group(1)}"] if m else []) + [name]:
        if shutil.which(candidate):
            return candidate
    sys.exit(f"{name} not found: apt-get install llvm")


def fuzz(exe: Path, work: Path, seconds: int, timeout: int, seed: int) -> tuple[int, str]:
    corpus, artifacts = work / "corpus", work / "artifacts"
    corpus.mkdir(parents=True, exist_ok=True)
    artifacts.mkdir(exist_ok=True)
    argv = [
        str(exe),
        f"-seed={seed}",
        f"-max_total_time={seconds}",
        f"-timeout={timeout}",
        "-rss_limit_mb=2048",
        "-max_len=1024",
        "-print_final_stats=1",
        f"-artifact_prefix={artifacts}/",
        str(corpus),
        str(SEEDS),
    ]
    print("# " + " ".join(argv), flush=True)
    log = work / "fuzz.log"
    with open(log, "w") as f:
        rc = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT).returncode
    return rc, log.read_text(errors="replace")


def coverage(exe: Path, work: Path) -> str:
    """llvm-cov's per-function table for the host-side functions, the corpus replayed once."""
    profraw, profdata = work / "cov.profraw", work / "cov.profdata"
    env = dict(os.environ, LLVM_PROFILE_FILE=str(profraw))
    subprocess.run(
        [str(exe), "-runs=0", str(work / "corpus"), str(SEEDS)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        check=True,
    )
    subprocess.run([llvm_tool("llvm-profdata"), "merge", "-o", str(profdata), str(profraw)], check=True)
    sources = [str(REPO / "rt_core/src/channels.c"), str(REPO / "rt_core/src/logformat.c")]
    report = subprocess.run(
        [llvm_tool("llvm-cov"), "report", "-show-functions", str(exe), f"-instr-profile={profdata}", *sources],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    keep = [
        line
        for line in report.splitlines()
        if line.startswith(("Name", "---")) or line.split()[:1] in ([f] for f in HOST_FUNCTIONS)
    ]
    return "\n".join(dict.fromkeys(keep))  # the header once, each function once


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=int, default=3600, help="fuzzing time (default 3600)")
    ap.add_argument("--timeout", type=int, default=10, help="seconds one input may take before it counts as a hang")
    ap.add_argument("--seed", type=int, default=None, help="libFuzzer's -seed (default: random, printed)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/xrf_bench/fuzz_channels"), help="builds, corpus, findings")
    ap.add_argument("--fresh", action="store_true", help="start from the repo's seeds (drop the kept corpus)")
    ap.add_argument("--no-coverage", action="store_true", help="skip the llvm-cov report")
    args = ap.parse_args()
    work: Path = args.work
    if args.fresh:
        shutil.rmtree(work / "corpus", ignore_errors=True)
    shutil.rmtree(work / "artifacts", ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    seed = args.seed if args.seed is not None else random.randrange(1, 2**31)

    print(f"# fuzz_channels long run   {time.strftime('%Y-%m-%dT%H:%M:%S%z')}")
    print(f"# host {os.uname().nodename} kernel {os.uname().release} cpus {os.cpu_count()}; seed {seed}")
    exe = build(work / "build", coverage=False)
    kept = len(list((work / "corpus").glob("*"))) if (work / "corpus").exists() else 0
    print(f"# corpus at start: {kept} inputs kept in {work / 'corpus'} + {len(list(SEEDS.iterdir()))} seeds")
    rc, out = fuzz(exe, work, args.seconds, args.timeout, seed)

    stats = dict(re.findall(r"^stat::(\w+):\s*(\d+)", out, re.M))
    status = re.findall(r"^#(\d+)\s+\w+\s+cov: (\d+) ft: (\d+) corp: (\d+)/(\S+)", out, re.M)
    runs, cov, ft, corp, corp_bytes = status[-1] if status else ("?",) * 5
    print(
        f"executions {stats.get('number_of_executed_units', runs)}  exec/s {stats.get('average_exec_per_sec', '?')}  "
        f"cov {cov}  ft {ft}  corpus {corp} ({corp_bytes})  new units {stats.get('new_units_added', '?')}  "
        f"slowest unit {stats.get('slowest_unit_time_sec', '?')} s  peak RSS {stats.get('peak_rss_mb', '?')} MB"
    )
    found = sorted((work / "artifacts").iterdir())
    if rc != 0 or found:
        tail = "\n".join(out.splitlines()[-60:])
        print(f"\nFOUND (exit {rc}):\n{tail}")
        for path in found:
            print(f"reproducer {path}; replay: {exe} {path}")
        return 1
    print("result: nothing found")
    if not args.no_coverage:
        cov_exe = build(work / "build-coverage", coverage=True)
        print("\n# host-side functions, the final corpus replayed in a coverage build (llvm-cov):")
        print(coverage(cov_exe, work))
    return 0


if __name__ == "__main__":
    sys.exit(main())
