"""What the kernel bounds for one run, set up before its controller starts, watched while it
runs, reported as layers of the run sandbox, and let go of when it ends.

- ``memory``, ``pids``, ``cpu``: the run's cgroup (cgroups.py): memory of all its processes with
  its /dev/shm and /tmp (``run_memory_mb``), processes and threads (``run_pids``), the CPUs it
  may use (``loop_cpus``: the loop's; with the launcher's RLIMIT_RTTIME and RLIMIT_RTPRIO, the
  ``cpu`` layer). The launcher moves the controller in before it execs (guest.py).
- ``disk``: the run folder is a file system of its own (disk.py, ``run_disk_mb``,
  ``run_files``); the kept run folders together stay under ``runs_total_mb`` (checked at start).

Over a limit the kernel has already refused (a fork, a page, a write); `over` tells the
supervisor, which stops the run with an alarm of that kind (``memory``, ``pids``, ``disk``,
``cpu``: runs.END_REASONS). docs/developers/security.md, "Resources the kernel bounds".
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import signal
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...runfolder import folder_bytes
from . import cgroups
from . import disk as run_disk
from . import disk_helper as run_disk_helper
from .cgroups import CgroupError, RunCgroup
from .disk import DiskError, DiskSpec

log = logging.getLogger("xrflab.supervisor")
MB = 1 << 20


class NoRoom(Exception):
    """No room on disk for another run (the total for all runs, or the data folder's disk)."""


def tag(data_dir: Path) -> str:
    """Names this appliance's run cgroups, whichever process it is (a restart finds its own)."""
    return hashlib.sha256(str(data_dir.resolve()).encode()).hexdigest()[:10]


def loop_cpus(settings: Any) -> set[int]:
    """The CPUs a run may use: ``loop_cpus`` if set, else the isolated ones (isolcpus=, the
    Pi's CPU 3), else $XRF_CPU of loop_env, else the last CPU the appliance may use."""
    if settings.loop_cpus:
        return cgroups.parse_cpus(settings.loop_cpus)
    with contextlib.suppress(OSError, ValueError):
        isolated = cgroups.parse_cpus(Path("/sys/devices/system/cpu/isolated").read_text().strip())
        if isolated:
            return isolated
    cpu = (settings.loop_env or {}).get("XRF_CPU")
    if cpu not in (None, "", "-1"):
        return {int(cpu)}
    return {max(os.sched_getaffinity(0))}


class RunDisk:
    """A run folder made a file system of its own: by the appliance itself (root) or by the
    root helper on its behalf (disk_helper.py)."""

    def __init__(self, run_dir: Path, image: Path | None = None, helper: str = "") -> None:
        self.run_dir, self.image, self.helper = run_dir, image, helper

    @property
    def bounded(self) -> bool:
        """The run folder is a file system of its own (not just a probe's answer from the helper)."""
        return self.image is not None or bool(self.helper)

    @classmethod
    def attach(cls, settings: Any, run_dir: Path, image: Path, gid: int) -> RunDisk:
        if os.geteuid() == 0:
            spec = DiskSpec(settings.run_disk_mb * MB, settings.run_files, os.getuid(), gid)
            runs = os.open(run_dir.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
            try:
                run_disk.attach(runs, run_dir.name, image, spec)
            finally:
                os.close(runs)
            return cls(run_dir, image)
        helper = settings.run_disk_helper
        req: dict[str, Any] = {"op": "ping"}
        if run_dir.name.isdigit():  # a run of the data folder; else a probe (xrf doctor): is the helper there?
            req = {"op": "attach", "run": int(run_dir.name), "mb": settings.run_disk_mb, "files": settings.run_files}
        try:
            run_disk_helper.request(helper, req)
        except (OSError, ValueError) as exc:
            raise DiskError(
                f"a non-root appliance needs the root helper for it (xrf-run-disk.socket, deploy/install): "
                f"{helper}: {exc.strerror if isinstance(exc, OSError) and exc.strerror else exc}"
            ) from exc
        except RuntimeError as exc:
            raise DiskError(f"the run-disk helper refused: {exc}") from exc
        return cls(run_dir, helper=helper if req["op"] == "attach" else "")

    def release(self) -> str:
        """Keep the run's files, remove its file system; what was not kept ("" if all was)."""
        if self.helper:
            answer = run_disk_helper.request(self.helper, {"op": "release", "run": int(self.run_dir.name)})
            return f"not kept: {answer['skipped']} ({'; '.join(answer['why'])})" if answer.get("skipped") else ""
        if self.image is None:
            return ""
        runs = os.open(self.run_dir.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            stats = run_disk.release(runs, self.run_dir.name, self.image)
        finally:
            os.close(runs)
        if stats is not None and stats.skipped_count:
            return f"not kept: {stats.skipped_count} ({'; '.join(stats.skipped[:3])})"
        return ""


@dataclass
class RunLimits:
    """One run's cgroup and file system, and which of the four layers hold (layer -> "" or why)."""

    run_dir: Path
    disk: RunDisk | None = None  # the run's file system, while mounted
    cgroup: RunCgroup | None = None
    layers: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    cpus: set[int] = field(default_factory=set)
    rttime_us: int = 0
    memory_mb: int = 0
    disk_mb: int = 0
    kept_note: str = ""  # what release() kept of the run's file system, for the record
    looks: int = 0  # how often `over` looked (tests: the guard's period)

    def launcher_config(self) -> dict[str, Any]:
        return {
            "cgroup_procs": self.cgroup.procs_files() if self.cgroup else [],
            "limit_layers": self.layers,
            "limit_notes": self.notes,
            "rttime_us": self.rttime_us,
        }

    def over(self, exit_signal: int = 0) -> tuple[str, str] | None:
        """(end reason, message) if the run went over one of its limits, else None."""
        self.looks += 1
        if exit_signal == signal.SIGXCPU:
            return "cpu", (
                f"a real-time thread of the controller ran {self.rttime_us // 1000} ms without blocking "
                "(RLIMIT_RTTIME): killed by SIGXCPU"
            )
        if self.cgroup is not None:
            with contextlib.suppress(OSError):
                ev = self.cgroup.events()
                if ev["oom_kill"]:
                    return "memory", (
                        f"the run went over its memory limit ({self.memory_mb} MB with its /dev/shm and "
                        f"/tmp): the kernel killed {ev['oom_kill']} of its processes"
                    )
                if ev["pids_max"]:
                    return "pids", (
                        f"the run went over its limit of processes and threads: the kernel refused "
                        f"{ev['pids_max']} fork(s)"
                    )
        if self.disk is not None and self.disk.bounded:
            with contextlib.suppress(OSError):
                u = run_disk.usage(self.run_dir)
                if u.full:
                    what = "files" if u.files_left <= 0 else f"{u.used // MB} MB of {u.size // MB} MB"
                    return "disk", f"the run folder is full ({what}): the kernel refuses its writes"
        return None

    @property
    def walks_disk(self) -> bool:
        """The run folder's size is watched by walking it (watched_disk_over): it has no file
        system of its own. Where it has one, the limits guard starts no walk at all (a worker
        thread's wake-up and the event loop's for its answer, every look, for nothing: issue 30
        item 4)."""
        return not (self.disk is not None and self.disk.bounded)

    def watched_disk_over(self) -> tuple[str, str] | None:
        """Where the `disk` layer is missing (an educator allowed the run without it): the run
        folder's size, walked, over ``run_disk_mb`` stops the run. A watch, not a bound: the run
        writes what it can between two looks (the limits guard looks every 4 s)."""
        if not self.walks_disk:
            return None
        used = folder_bytes(self.run_dir)
        if used <= self.disk_mb * MB:
            return None
        return "disk", (
            f"the run folder holds {used // MB} MB, over the limit of {self.disk_mb} MB (watched: it has no "
            "file system of its own here)"
        )

    def release(self) -> None:
        """After the run: keep its files (copied out of its file system), remove the file
        system and the cgroup. Safe to call twice."""
        if self.disk is not None:
            try:
                self.kept_note = self.disk.release()
            except (OSError, RuntimeError) as exc:
                log.warning("run folder %s: releasing its file system failed: %s", self.run_dir, exc)
            self.disk = None
        if self.cgroup is not None:
            if not self.cgroup.remove():
                log.warning("run cgroup %s still busy: removed at the next start", self.cgroup.name)
            self.cgroup = None


def prepare(settings: Any, name: str, run_dir: Path, image: Path, gid: int) -> RunLimits:
    """Set up the run's cgroup and file system (blocking: run it in a thread). A layer that
    cannot be had is reported, not raised (the launcher refuses the run unless an educator
    allowed that). Raises NoRoom when the disk has no room for another run."""
    lim = RunLimits(run_dir, memory_mb=settings.run_memory_mb, disk_mb=settings.run_disk_mb)
    lim.cpus = loop_cpus(settings)
    lim.rttime_us = max(0, settings.rt_time_ms) * 1000
    try:
        lim.cgroup = RunCgroup.create(
            name, cgroups.Spec(settings.run_memory_mb * MB, settings.run_pids, cgroups.format_cpus(lim.cpus))
        )
        for layer in ("memory", "pids", "cpu"):
            lim.layers[layer] = ""
        lim.notes.append(
            f"run cgroup: {settings.run_memory_mb} MB, {settings.run_pids} processes, CPU {cgroups.format_cpus(lim.cpus)}"
        )
        if set(os.sched_getaffinity(0)) <= lim.cpus:
            lim.notes.append("the run's CPUs are all the appliance's: its cpuset keeps nothing apart")
    except CgroupError as exc:
        for layer in ("memory", "pids", "cpu"):
            lim.layers[layer] = str(exc)
    try:
        _disk(settings, lim, run_dir, image, gid)
    except BaseException:
        lim.release()
        raise
    return lim


def _disk(settings: Any, lim: RunLimits, run_dir: Path, image: Path, gid: int) -> None:
    size = settings.run_disk_mb * MB
    runs_dir = run_dir.parent
    kept = run_disk.kept_bytes(runs_dir)
    if kept + size > settings.runs_total_mb * MB:
        raise NoRoom(
            f"the kept runs use {kept // MB} MB of the {settings.runs_total_mb} MB for all runs and a run may "
            f"write {settings.run_disk_mb} MB: delete old runs first"
        )
    st = os.statvfs(runs_dir)
    free = st.f_bavail * st.f_frsize
    if free < 2 * size:  # the (sparse) image may fill, and its copy when the run ends
        raise NoRoom(f"{free // MB} MB free on the data folder's disk, a run needs {2 * settings.run_disk_mb} MB")
    try:
        lim.disk = RunDisk.attach(settings, run_dir, image, gid)
    except DiskError as exc:
        lim.layers["disk"] = str(exc)
        return
    lim.layers["disk"] = ""
    if run_disk.is_mounted(run_dir):
        u = run_disk.usage(run_dir)
        lim.notes.append(f"run folder: its own file system, {u.available // MB} MB and {u.files_left} files")
    else:  # a probe of a non-root appliance: the helper answered
        lim.notes.append(
            f"run folders: file systems of their own, made by the root helper ({settings.run_disk_helper})"
        )


def sweep(settings: Any, live: set[Path] | None = None) -> list[str]:
    """What an earlier appliance of this data folder left (killed before a run's end): run
    file systems (copied out, removed) and empty run cgroups."""
    done = []
    names = {p.name for p in live or set()}
    if os.geteuid() == 0:
        done += run_disk.sweep(settings.runs_dir, settings.data_dir / run_disk.IMAGES, names)
    elif Path(settings.run_disk_helper).exists():
        with contextlib.suppress(OSError, RuntimeError, ValueError):
            live_ids = [int(n) for n in names if n.isdigit()]
            done += run_disk_helper.request(settings.run_disk_helper, {"op": "sweep", "live": live_ids})["done"]
    kept = cgroups.sweep(tag(settings.data_dir))
    if kept:
        done.append(f"run cgroups still in use: {', '.join(kept)}")
    return done
