"""What a test session leaves behind: processes it started, shared-memory objects, files in the
checkout, mounts (a run folder's own file system) and run cgroups. tests/conftest.py takes a `Snapshot` when the session starts and fails the session if
`Snapshot.leftovers()` finds anything at its end (then removes it, so the machine stays clean).

How a process is known to be the suite's: it carries the session's marker in its environment
(``XRF_TEST_SESSION``, set before any test starts, inherited by every child), or it is the run
sandbox's launcher of a run whose folder is in the session's temporary folder (the launcher gets
an allow-listed environment, so no marker; its XRF_RUN_DIR names the run), or it is a descendant of
either. A rerun server orphaned by a killed appliance (parent 1) is found by its marker.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

MARKER = "XRF_TEST_SESSION"
SHM = Path("/dev/shm")
# Objects of ours in /dev/shm: run segments and their folders, test segments, Fast DDS's
# shared-memory transport (the ROS tests), cyclictest's, lttng-ust's wait page (below).
SHM_PREFIXES = ("xrf", "fastdds", "sem.fastdds", "fast_datasharing", "cyclictest", "lttng-ust-wait")
# Objects libraries leave by design, removed at the session's end once nobody maps them (as their
# own tools would): Fast DDS's segments (kept for the next participant, or `fastdds shm clean`),
# and lttng-ust's wait page (liblttng-ust comes bundled in the ROS 2 wheels: every process that
# loads rclpy creates /dev/shm/lttng-ust-wait-<major>[-<uid>] to wait for a tracing daemon, and no
# process removes it; on a fresh machine the suite's ROS tests would leave it behind).
RECLAIMED = ("fastdds", "sem.fastdds", "lttng-ust-wait")
# A session a test starts (tests/testing/test_leaks.py, tests/deploy/test_fresh_background.py) runs
# beside the parent session's other xdist workers, whose appliances make run cgroups and segments
# that may be empty or unmapped for a moment: the nested session would take them for its own
# leftovers and remove them under a running test. With this set it checks its own processes and
# files as always, /dev/shm objects with this prefix only, and no run cgroup.
NESTED_ENV = "XRF_LEAK_NESTED_SHM"
# Ignored paths of the checkout that tests may fill (caches, the venv, and test-results/: the UI
# tests' screenshots, the suite's one declared output folder, git-ignored).
IGNORED = (".venv/", ".cache/", ".pytest_cache/", ".hypothesis/", "__pycache__/", ".egg-info/", "test-results/")


def _environ(pid: int) -> list[bytes]:
    try:
        return Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return []


def _stat(pid: int) -> tuple[str, int]:
    """(state, parent pid) or ("", 0) when gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return fields[0], int(fields[1])
    except (OSError, IndexError, ValueError):
        return "", 0


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:160]
    except OSError:
        return "?"


def _pids() -> set[int]:
    return {int(e) for e in os.listdir("/proc") if e.isdigit()}


def descendants(pid: int) -> set[int]:
    """Every process below `pid` now (parent links from /proc)."""
    parent = {p: _stat(p)[1] for p in _pids()}
    found, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, q in parent.items() if q in frontier} - found
        found |= frontier
    return found


def _mounts() -> set[str]:
    out = set()
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/mountinfo").read_text().splitlines():
            fields = line.split()
            if len(fields) > 4:
                out.add(fields[4].replace("\\040", " "))
    return out


def _run_cgroups() -> set[str]:
    from xrflab.server.runs import cgroups

    try:
        places = cgroups.find()
    except cgroups.CgroupError:
        return set()
    out = set()
    for base in {p.base for p in places.values()}:
        with contextlib.suppress(OSError):
            out |= {str(e) for e in base.iterdir() if e.name.startswith(cgroups.PREFIX)}
    return out


def _untracked(repo: Path) -> set[str]:
    try:
        out = subprocess.run(
            ["git", "-C", str(repo), "status", "--porcelain", "--ignored", "--untracked-files=all"],
            capture_output=True,
            text=True,
            timeout=60,
        ).stdout
    except (OSError, subprocess.TimeoutExpired):
        return set()
    names = {line[3:] for line in out.splitlines() if line[:2] in ("??", "!!")}
    return {n for n in names if not any(part in n for part in IGNORED)}


@dataclass
class Snapshot:
    marker: str
    # The session's own temporary folder (pytest's basetemp, /tmp/pytest-of-<user>/pytest-<N>): not
    # its parent, which every session of the user shares (others may be running beside this one).
    temp_root: Path
    repo: Path
    pids: set[int] = field(default_factory=set)
    shm: set[str] = field(default_factory=set)
    files: set[str] = field(default_factory=set)
    me: int = field(default_factory=os.getpid)
    mounts: set[str] = field(default_factory=set)
    cgroups: set[str] = field(default_factory=set)

    @classmethod
    def take(cls, marker: str, temp_root: Path, repo: Path) -> Snapshot:
        shm = set(os.listdir(SHM)) if SHM.is_dir() else set()
        return cls(marker, temp_root, repo, _pids(), shm, _untracked(repo), mounts=_mounts(), cgroups=_run_cgroups())

    def mounts_left(self) -> set[str]:
        """Mounts made during the session under its temporary folder or the checkout (a run
        folder's file system, server/runs/disk.py), still mounted here."""
        roots = (str(self.temp_root) + "/", str(self.repo) + "/")
        return {m for m in _mounts() - self.mounts if m.startswith(roots)}

    def cgroups_left(self) -> set[str]:
        """Run cgroups (server/runs/cgroups.py) made during the session and left empty: a run cgroup
        with processes in it is a live run of another session's appliance."""
        left: set[str] = set()
        if os.environ.get(NESTED_ENV):
            return left
        for path in _run_cgroups() - self.cgroups:
            with contextlib.suppress(OSError):
                if not Path(path, "cgroup.procs").read_text().strip():
                    left.add(path)
        return left

    def _ours(self, pid: int) -> bool:
        env = _environ(pid)
        if f"{MARKER}={self.marker}".encode() in env:
            return True
        run_dir = next((e[len(b"XRF_RUN_DIR=") :] for e in env if e.startswith(b"XRF_RUN_DIR=")), b"")
        return bool(run_dir) and run_dir.decode(errors="replace").startswith(str(self.temp_root))

    def processes(self) -> dict[int, str]:
        """Processes of this session still alive (not this one, nor what existed before it)."""
        new = _pids() - self.pids - {self.me}
        parent = {p: _stat(p)[1] for p in new}
        found = {p for p in new if _stat(p)[0] not in ("", "Z") and self._ours(p)}
        grew = True
        while grew:  # and everything below them (a controller runs as another user: no environ to read)
            below = {p for p in new if parent.get(p) in found and _stat(p)[0] not in ("", "Z")} - found
            found |= below
            grew = bool(below)
        # Our own children still running are ours too (a fixture that forgot one).
        found |= {p for p in new if parent.get(p) == self.me and _stat(p)[0] not in ("", "Z")}
        return {p: _cmdline(p) for p in sorted(found)}

    def shm_objects(self) -> set[str]:
        now = set(os.listdir(SHM)) if SHM.is_dir() else set()
        nested = os.environ.get(NESTED_ENV)
        new = {n for n in now - self.shm if n.startswith((nested,) if nested else SHM_PREFIXES)}
        return new - self._in_use_by_others(new) - self._others_by_name_or_owner(new)

    def _others_by_name_or_owner(self, names: set[str]) -> set[str]:
        """Objects this session cannot have made: a normal user's session makes only objects of
        its own uid (root's belong to root's sessions beside it); and xrf-test-<pid>-* /
        xrf-lab-<pid>-* name their creator (a test process, an appliance), which, while it
        lives, is another session's if it is not this one's."""
        me = os.getuid()
        ours = set(self.processes()) | {self.me}
        others: set[str] = set()
        for n in names:
            try:
                if me != 0 and os.lstat(SHM / n).st_uid != me:
                    others.add(n)
                    continue
            except OSError:
                continue
            parts = n.split("-")
            if n.startswith(("xrf-test-", "xrf-lab-")) and len(parts) > 2 and parts[2].isdigit():
                pid = int(parts[2])
                if pid not in ours and _stat(pid)[0] not in ("", "Z"):
                    others.add(n)
        return others

    def _in_use_by_others(self, names: set[str]) -> set[str]:
        """Of `names`, those a live process that is not this session's maps: another test session
        or appliance on the same machine (an object nobody maps any more is counted as ours)."""
        if not names:
            return set()
        ours = set(self.processes()) | {self.me}
        busy: set[str] = set()
        for pid in _pids() - ours:
            try:
                maps = Path(f"/proc/{pid}/maps").read_text()
            except OSError:
                continue
            busy |= {n for n in names if f"/dev/shm/{n}" in maps}
        return busy

    def reclaim_by_design(self) -> list[str]:
        """Remove the objects of RECLAIMED this session created that no process maps any more.
        The ROS tests run Fast DDS over UDP, but the appliance's bridge still makes data-sharing
        segments; lttng-ust's page is made by any process that loads rclpy (the session's own, when
        a test imports it in-process). Only objects no other process maps are removed, as Fast DDS
        itself would (a name removed under this process's mapping leaves the mapping valid)."""
        stale = {n for n in self.shm_objects() if n.startswith(RECLAIMED)}
        if not stale:
            return []
        for pid in _pids() - {os.getpid()}:  # this process (the session's, about to end) may map them
            try:
                maps = Path(f"/proc/{pid}/maps").read_text()
            except OSError:
                continue
            stale -= {n for n in stale if f"/dev/shm/{n}" in maps}
        for name in stale:
            with contextlib.suppress(OSError):
                (SHM / name).unlink()
        return sorted(stale)

    def leftovers(self, grace_s: float = 10.0) -> list[str]:
        """Everything left, after waiting up to `grace_s` for things that are on their way out."""
        deadline = time.monotonic() + grace_s
        while True:
            procs, shm = self.processes(), self.shm_objects()
            files = _untracked(self.repo) - self.files
            mounts, groups = self.mounts_left(), self.cgroups_left()
            if not (procs or shm or files or mounts or groups) or time.monotonic() > deadline:
                break
            time.sleep(0.25)
        report = [f"process {p}: {c}" for p, c in procs.items()]
        report += [f"/dev/shm/{n}" for n in sorted(shm)]
        report += [f"file in the checkout: {n}" for n in sorted(files)]
        report += [f"mount: {m}" for m in sorted(mounts)]
        report += [f"run cgroup: {g}" for g in sorted(groups)]
        return report

    def clean(self) -> None:
        """Remove what leftovers() reported (after it was reported)."""
        for pid in self.processes():
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        for mount in sorted(self.mounts_left(), reverse=True):
            subprocess.run(["umount", "--lazy", mount], capture_output=True, timeout=30)
        for group in self.cgroups_left():
            with contextlib.suppress(OSError):
                os.rmdir(group)
        for name in self.shm_objects():
            path = SHM / name
            with contextlib.suppress(OSError):
                if path.is_dir():
                    import shutil

                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink()
