"""bench/arm64/rehearse's own handling (issue 30 item 3), without the emulation (that takes most
of an hour and runs on demand): bad arguments are refused before anything is made, its cache must
be outside the repository, and --clean removes what it made there and nothing else."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from xrf_testing.deploy_support import REPO

SCRIPT = REPO / "bench" / "arm64" / "rehearse"


def _run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(SCRIPT), *args], capture_output=True, text=True, timeout=30, env={**os.environ, **(env or {})}
    )


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--frobnicate"], "unknown argument --frobnicate"),
        (["--port", "80x"], "--port must be a number"),
        (["--cache", "relative/dir"], "--cache must be an absolute path"),
        (["--cache", str(REPO / ".cache" / "arm64")], "--cache must be outside the repository"),
        (["--cache", "/"], "--cache must not be /"),
    ],
)
def test_bad_arguments_are_refused_before_anything_is_made(args: list[str], says: str, tmp_path: Path) -> None:
    p = _run(*args, env={"XRF_ARM64_CACHE": str(tmp_path / "cache")})
    assert p.returncode == 2, p
    assert says in p.stderr, p.stderr
    assert not (tmp_path / "cache").exists()
    assert not (REPO / ".cache" / "arm64").exists()


def test_help_describes_the_steps() -> None:
    p = _run("--help")
    assert p.returncode == 0, p.stderr
    for step in ("root", "copy", "clone", "install", "serve", "--clean", "/var/cache/xrf-arm64-rehearsal"):
        assert step in p.stdout, step


def test_clean_removes_the_cached_root_and_left_copies_only(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    made = [cache / "root-bookworm-arm64" / "etc", cache / "run.4242" / "root", cache / "root-bookworm-arm64.tmp"]
    for d in made:
        d.mkdir(parents=True)
        (d / "f").write_text("x")
    (cache / "notes.txt").write_text("not the script's")
    p = _run("--clean", "--cache", str(cache))
    assert p.returncode == 0, p.stderr
    assert sorted(x.name for x in cache.iterdir()) == ["notes.txt"]
    (cache / "notes.txt").unlink()
    assert _run("--clean", "--cache", str(cache)).returncode == 0
    assert not cache.exists()  # empty: removed with its last root


def test_a_normal_user_is_told_it_needs_root(tmp_path: Path) -> None:
    # As root, the same check as user nobody (setpriv): root would go on to debootstrap.
    who = [] if os.geteuid() != 0 else ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
    cache = Path("/tmp") / f"xrf-arm64-needs-root-{os.getpid()}"  # a place nobody may also name
    p = subprocess.run([*who, str(SCRIPT), "--cache", str(cache)], capture_output=True, text=True, timeout=30)
    assert p.returncode == 2 and "needs root" in p.stderr, p
    assert not cache.exists()
