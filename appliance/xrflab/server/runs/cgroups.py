"""A cgroup per run: its memory, its process count and its CPUs, bounded by the kernel.

The run sandbox's launcher moves the controller into the run's cgroup before it execs
(guest.py, ``cgroup_procs``), so the bound holds from the controller's first instruction and
for everything it forks. Memory is charged to the cgroup of the process that touches a page:
the controller's heap, its children's, and the tmpfs pages it writes in its /dev/shm folder and
its /tmp, all of them together.

Two kernels' interfaces, found from /proc/self/mountinfo and /proc/self/cgroup:

- cgroup v1 (one hierarchy per controller, e.g. this CI VM): a folder ``<name>`` under the
  appliance's own cgroup in each of the memory, pids and cpuset hierarchies.
  ``memory.limit_in_bytes`` (+ ``memory.memsw.limit_in_bytes`` where swap is accounted),
  ``pids.max``, ``cpuset.cpus``/``cpuset.mems``. An OOM kill shows in ``memory.oom_control``.
- cgroup v2 (the unified hierarchy; the Pi under systemd with ``Delegate=``): one folder
  ``<name>`` beside the appliance's own leaf. ``memory.max``, ``memory.swap.max`` 0 and
  ``memory.oom.group`` (an OOM kills the whole run), ``pids.max``, ``cpuset.cpus``. The
  appliance needs write access there: root, or a delegated subtree. Because a v2 cgroup with
  processes may not give its controllers to children, an appliance alone in its service's cgroup
  first moves itself to ``xrf-appliance/`` below it (systemd's ``DelegateSubgroup=xrf-appliance``
  does the same).

Folders are named ``xrf-run-<tag>-<run>``: ``tag`` is the appliance's data folder's, so a
restarted appliance removes what its predecessor left (`sweep`) and never another's.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

CONTROLLERS = ("memory", "pids", "cpuset")
PREFIX = "xrf-run-"
APPLIANCE_LEAF = "xrf-appliance"  # v2: where the appliance moves itself (systemd's DelegateSubgroup=)


class CgroupError(Exception):
    """A cgroup could not be had; the message says why (shown as the missing layer's reason)."""


@dataclass(frozen=True)
class Spec:
    memory_bytes: int
    pids: int
    cpus: str  # cpuset list, "1" or "2-3"


@dataclass(frozen=True)
class Place:
    """Where run cgroups of one controller are made."""

    version: int  # 1 or 2
    base: Path  # the folder the run's folder is made in


def _mountinfo() -> list[tuple[str, str, list[str]]]:
    """(mount point, file system type, super options) of every mount we see."""
    out = []
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/mountinfo").read_text().splitlines():
            left, _, right = line.partition(" - ")
            fields, rest = left.split(), right.split()
            if len(fields) >= 5 and len(rest) >= 3:
                point = fields[4].replace("\\040", " ")
                out.append((point, rest[0], rest[2].split(",")))
    return out


def _own_cgroups() -> dict[str, str]:
    """Controller name (v1) or "" (v2) -> the appliance's own cgroup path."""
    out: dict[str, str] = {}
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            parts = line.split(":", 2)
            if len(parts) == 3:
                for c in parts[1].split(",") if parts[1] else [""]:
                    out[c] = parts[2]
    return out


def _under(mount: str, path: str) -> Path:
    return Path(mount) / path.lstrip("/")


def _read(path: Path) -> str:
    return path.read_text()


def _write(path: Path, value: str) -> None:
    """One write(2) of `value` (a cgroup file takes one value per write)."""
    fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
    try:
        os.write(fd, value.encode())
    finally:
        os.close(fd)


def counters(path: Path | str) -> dict[str, int]:
    """A "key value" per line file (memory.events, pids.events, cpu.stat, memory.oom_control), or
    one number (memory.failcnt: as "value"). Read with one os.read, no text file object: the
    limits guard reads two of these per look per run. At most 64 KiB and 64 lines."""
    out: dict[str, int] = {}
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        try:
            data = os.read(fd, 65536)
        finally:
            os.close(fd)
    except OSError:
        return out
    for line in data.splitlines()[:64]:
        key, _, value = line.strip().partition(b" ")
        with contextlib.suppress(ValueError):
            if value:
                out[key.decode("ascii", "replace")[:40]] = int(value)
            else:
                out["value"] = int(key)
    return out


def find() -> dict[str, Place]:
    """Where each controller's run cgroups go; raises CgroupError naming what is missing."""
    mounts = _mountinfo()
    own = _own_cgroups()
    places: dict[str, Place] = {}
    v2_mount = next((m for m, fs, _ in mounts if fs == "cgroup2"), None)
    v2_available: set[str] = set()
    if v2_mount is not None and "" in own:
        with contextlib.suppress(OSError):
            v2_available = set(_read(_under(v2_mount, own[""]) / "cgroup.controllers").split())
        with contextlib.suppress(OSError):  # the root cgroup has no cgroup.controllers of its own use
            if own[""] == "/":
                v2_available = set(_read(Path(v2_mount) / "cgroup.controllers").split())
    for c in CONTROLLERS:
        v1 = next((m for m, fs, opts in mounts if fs == "cgroup" and c in opts), None)
        if v1 is not None and c in own:
            places[c] = Place(1, _under(v1, own[c]))
        elif v2_mount is not None and c in v2_available:
            places[c] = Place(2, _v2_base(Path(v2_mount), own[""]))
    if os.geteuid() != 0 and any(p.version == 1 for p in places.values()):
        # v1 lets a process move another into a cgroup only as root or as the same user; the
        # controller runs as another uid than the appliance. v2 checks the folders' permissions.
        raise CgroupError(
            "cgroup v1 hierarchies: only a root appliance can place its runs (cgroup v2 with delegation can)"
        )
    missing = [c for c in CONTROLLERS if c not in places]
    if missing:
        raise CgroupError(f"no {', '.join(missing)} cgroup controller available to the appliance")
    for c, place in places.items():
        if not os.access(place.base, os.W_OK):
            raise CgroupError(
                f"no write access to {place.base} ({c}): the appliance needs root or a delegated cgroup "
                "(systemd Delegate=yes, see docs/install/pi.md)"
            )
    return places


def _v2_base(mount: Path, own: str) -> Path:
    """The v2 folder run cgroups are made in: the root, or the parent of our own leaf."""
    here = _under(str(mount), own)
    if own == "/":
        return here
    if here.name == APPLIANCE_LEAF:
        return here.parent
    return here  # becomes the base once we moved ourselves below it (prepare_v2)


def prepare_v2(base: Path) -> None:
    """v2: give the base's controllers to its children. A cgroup holding processes may not, so
    the processes in it (the appliance, nothing else under a systemd service) move to
    ``xrf-appliance/`` first."""
    enabled = set(_read(base / "cgroup.subtree_control").split())
    if set(CONTROLLERS) <= enabled:
        return
    procs = [p for p in _read(base / "cgroup.procs").split() if p]
    if procs and base != base.parent:
        leaf = base / APPLIANCE_LEAF
        leaf.mkdir(exist_ok=True)
        for pid in procs:
            with contextlib.suppress(ProcessLookupError):
                _write(leaf / "cgroup.procs", pid)
    _write(base / "cgroup.subtree_control", " ".join(f"+{c}" for c in CONTROLLERS))


def parse_cpus(text: str) -> set[int]:
    """A cpuset list ("0-2,5") as a set of CPU numbers."""
    cpus: set[int] = set()
    for part in filter(None, (p.strip() for p in text.split(","))):
        first, _, last = part.partition("-")
        cpus.update(range(int(first), int(last or first) + 1))
    return cpus


def format_cpus(cpus: Iterable[int]) -> str:
    return ",".join(str(c) for c in sorted(cpus))


@dataclass
class RunCgroup:
    """One run's cgroup folders (one per v1 hierarchy, or one v2 folder)."""

    name: str
    places: dict[str, Place]
    made: list[Path] = field(default_factory=list)
    _event_files: tuple[str, str] | None = field(default=None, repr=False, compare=False)

    def folder(self, controller: str) -> Path:
        return self.places[controller].base / self.name

    def folders(self) -> list[Path]:
        return list(dict.fromkeys(self.folder(c) for c in CONTROLLERS))

    def procs_files(self) -> list[str]:
        """Where the launcher writes the controller's pid (one per folder)."""
        return [str(f / "cgroup.procs") for f in self.folders()]

    @classmethod
    def create(cls, name: str, spec: Spec, places: dict[str, Place] | None = None) -> RunCgroup:
        places = places or find()
        cg = cls(name, places)
        try:
            for place in {p.base for p in places.values() if p.version == 2}:
                prepare_v2(place)
            for folder in cg.folders():
                with contextlib.suppress(FileNotFoundError, OSError):
                    folder.rmdir()  # an empty leftover of the same name (a run id reused after a reset)
                folder.mkdir()
                cg.made.append(folder)
            cg._limit(spec)
        except OSError as exc:
            cg.remove()
            raise CgroupError(f"cannot set up the run's cgroup {name}: {exc}") from exc
        return cg

    def _limit(self, spec: Spec) -> None:
        mem, pids, cpus = self.folder("memory"), self.folder("pids"), self.folder("cpuset")
        if self.places["memory"].version == 1:
            _write(mem / "memory.limit_in_bytes", str(spec.memory_bytes))
            if (mem / "memory.memsw.limit_in_bytes").exists():  # swap counted too: no way around the limit
                _write(mem / "memory.memsw.limit_in_bytes", str(spec.memory_bytes))
        else:
            _write(mem / "memory.max", str(spec.memory_bytes))
            if (mem / "memory.swap.max").exists():
                _write(mem / "memory.swap.max", "0")
            if (mem / "memory.oom.group").exists():  # an OOM ends the whole run, not one process of it
                _write(mem / "memory.oom.group", "1")
        _write(pids / "pids.max", str(spec.pids))
        parent = cpus.parent
        allowed = parse_cpus(
            _read(parent / ("cpuset.cpus" if self.places["cpuset"].version == 1 else "cpuset.cpus.effective"))
        )
        wanted = parse_cpus(spec.cpus)
        if not wanted or not wanted <= allowed:
            raise OSError(
                0, f"CPUs {spec.cpus!r} are not all available to the appliance (its cpuset: {format_cpus(allowed)})"
            )
        if self.places["cpuset"].version == 1:
            _write(cpus / "cpuset.mems", _read(parent / "cpuset.mems").strip())  # v1: no tasks without mems
        _write(cpus / "cpuset.cpus", spec.cpus)

    def events(self) -> dict[str, int]:
        """``oom_kill``: processes the kernel killed for the memory limit; ``pids_max``: forks
        refused for the process limit. Read every 4 s per run (watch.limits_guard): two
        small files, nothing else (the memory peak it also read was used by nobody)."""
        if self._event_files is None:  # the paths once (pathlib's joins cost more than the reads)
            mem, pids = self.folder("memory"), self.folder("pids")
            v1 = self.places["memory"].version == 1
            self._event_files = (
                str(mem / ("memory.oom_control" if v1 else "memory.events")),
                str(pids / "pids.events"),
            )
        mem_file, pids_file = self._event_files
        ev = counters(mem_file)
        oom = max(ev.get("oom_kill", 0), ev.get("oom", 0), ev.get("oom_group_kill", 0))
        return {"oom_kill": oom, "pids_max": counters(pids_file).get("max", 0)}

    def pids(self) -> list[int]:
        out: set[int] = set()
        for f in self.folders():
            with contextlib.suppress(OSError):
                out.update(int(p) for p in _read(f / "cgroup.procs").split())
        return sorted(out)

    def remove(self, wait_s: float = 2.0) -> bool:
        """Remove the folders (the run's processes must be gone; a dying one may take a moment).
        True when nothing is left."""
        deadline = time.monotonic() + wait_s
        left = list(self.made or self.folders())
        while left:
            still = []
            for folder in left:
                try:
                    folder.rmdir()
                except FileNotFoundError:
                    pass
                except OSError:
                    still.append(folder)
            left = still
            if not left or time.monotonic() > deadline:
                break
            time.sleep(0.02)
        self.made = left
        return not left


def sweep(tag: str, places: dict[str, Place] | None = None) -> list[str]:
    """Remove the empty run cgroups an earlier appliance of this data folder left (killed
    before it could); a folder still holding processes (a live orphaned run) is kept. Returns
    what is still there."""
    try:
        places = places or find()
    except CgroupError:
        return []
    kept = []
    for base in {p.base for p in places.values()}:
        with contextlib.suppress(OSError):
            for entry in base.iterdir():
                if entry.name.startswith(f"{PREFIX}{tag}-") and entry.is_dir():
                    try:
                        entry.rmdir()
                    except OSError:
                        kept.append(str(entry))
    return kept
