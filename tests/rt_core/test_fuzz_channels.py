"""The libFuzzer harness of channels.c's host side (rt_core/fuzz/fuzz_channels.c, issue 26), run for
a bounded budget from the seed corpus kept in the repo: any sanitizer report (ASan, UBSan, a leak),
broken contract or hang fails the test, which names the reproducer (kept in .cache/fuzz-channels/
findings/) and shows how to replay it. The long run is bench/rt_core/fuzz_channels.py.

The budget (FUZZ_SECONDS of fuzzing, plus a build of a few seconds the first time; later sessions
reuse the build in the ignored .cache/ folder) is fixed; so is libFuzzer's -seed. The harness races
a second thread against the host's reads on purpose, so two runs need not take the same path."""

from __future__ import annotations

import base64
import fcntl
import os
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SEEDS = REPO / "rt_core/fuzz/corpus/channels"
CACHE = REPO / ".cache/fuzz-channels"
FUZZ_SECONDS = 30
# One input may run for this long before libFuzzer calls it a hang: every host call is bounded,
# the slowest honest input takes well under a second here even with the other CPU busy.
INPUT_TIMEOUT_S = 10


def build_fuzzer(build: Path) -> Path:
    """Configure (clang, XRF_FUZZ=ON, -Werror) and build the harness incrementally in `build`."""
    for tool in ("clang", "clang++"):
        assert shutil.which(tool), f"{tool} not found: ./lab installs it (APT_PACKAGES: clang, libclang-rt-14-dev)"
    env = dict(os.environ, CC="clang", CXX="clang++")
    if not (build / "CMakeCache.txt").exists():
        r = subprocess.run(
            ["cmake", "-S", str(REPO / "rt_core"), "-B", str(build), "-DXRF_FUZZ=ON", "-DXRF_WERROR=ON"],
            env=env,
            capture_output=True,
            text=True,
        )
        assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    r = subprocess.run(
        ["cmake", "--build", str(build), "--target", "fuzz_channels", "-j2"], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    return build / "fuzz_channels"


@pytest.fixture(scope="session")
def fuzzer() -> Iterator[Path]:
    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE / "lock", "w") as lock:  # sessions in parallel share the build
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield build_fuzzer(CACHE / "build")


def final_stats(output: str) -> dict[str, str]:
    """libFuzzer's -print_final_stats lines and the last status line's cov/ft/corp figures."""
    stats = dict(re.findall(r"^stat::(\w+):\s*(\d+)", output, re.M))
    status = re.findall(r"^#(\d+)\s+\w+\s+cov: (\d+) ft: (\d+) corp: (\d+)", output, re.M)
    if status:
        stats.update(zip(("runs", "cov", "ft", "corpus"), status[-1]))
    return stats


def test_seed_corpus_is_the_harness_output(fuzzer: Path, tmp_path: Path) -> None:
    """The corpus in the repo is what the harness writes (its opcodes are defined there only):
    a change of the input format that forgets the seeds fails here."""
    r = subprocess.run([str(fuzzer)], env=dict(os.environ, XRF_FUZZ_WRITE_SEEDS=str(tmp_path)), capture_output=True)
    assert r.returncode == 0, r.stderr.decode()[-2000:]
    written = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    kept = {p.name: p.read_bytes() for p in SEEDS.iterdir()}
    assert written == kept, (
        "rt_core/fuzz/corpus/channels/ is stale: regenerate it with XRF_FUZZ_WRITE_SEEDS=<that folder>"
    )


def test_host_readers_survive_fuzzing(fuzzer: Path, tmp_path: Path) -> None:
    work = tmp_path / "corpus"  # new inputs go here, never into the repo's seeds
    work.mkdir()
    artifacts = tmp_path / "artifacts"
    artifacts.mkdir()
    argv = [
        str(fuzzer),
        "-seed=1",
        f"-max_total_time={FUZZ_SECONDS}",
        f"-timeout={INPUT_TIMEOUT_S}",
        "-rss_limit_mb=2048",
        "-max_len=1024",
        "-print_final_stats=1",
        f"-artifact_prefix={artifacts}/",
        str(work),
        str(SEEDS),
    ]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=FUZZ_SECONDS + 120)
    stats = final_stats(r.stderr)
    print(
        f"fuzz_channels: {stats.get('number_of_executed_units', '?')} executions in {FUZZ_SECONDS} s, "
        f"{stats.get('average_exec_per_sec', '?')} exec/s, cov {stats.get('cov', '?')} ft {stats.get('ft', '?')}, "
        f"corpus {stats.get('corpus', '?')}, peak RSS {stats.get('peak_rss_mb', '?')} MB"
    )
    found = sorted(artifacts.iterdir())
    if r.returncode == 0 and not found:
        assert int(stats.get("number_of_executed_units", 0)) > 0, r.stderr[-3000:]
        return
    kept = CACHE / "findings"
    kept.mkdir(parents=True, exist_ok=True)
    lines = []
    for path in found:
        shutil.copy(path, kept / path.name)
        lines.append(
            f"reproducer {kept / path.name} (base64 {base64.b64encode(path.read_bytes()).decode()}); "
            f"replay: {fuzzer} {kept / path.name}"
        )
    report = "\n".join(r.stderr.splitlines()[-80:])
    pytest.fail(f"fuzz_channels failed (exit {r.returncode}):\n{report}\n" + "\n".join(lines), pytrace=False)
