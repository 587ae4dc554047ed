"""The sandbox process a student's build runs in.

The appliance starts it (``python -m xrflab.projects.builder --sandbox CONFIG -- CMD``, see
``sandbox_launch.py``) and it confines itself before exec'ing the build. A process of its own,
not code in the appliance, because each step changes the calling process for good (namespaces,
user, limits). Before the exec it:

- leaves the appliance's session (``setsid``), so the whole build can be killed as a group;
- gets a PID namespace of its own (``unshare(CLONE_NEWPID)``, then a fork: the build's first
  process is the namespace's init, killed with the sandbox process by ``PR_SET_PDEATHSIG``).
  When it dies the kernel kills every other process in the namespace, however it detached
  (``setsid``, double fork): ending a build ends exactly that build, never another appliance's
  build that runs as the same build user. An IPC namespace as well (SysV IPC, POSIX queues);
- takes the network away: a new network namespace with only a downed loopback
  (``unshare(CLONE_NEWNET)``; without root, inside a new user namespace); if the kernel refuses,
  the build goes on and the log says so (``sandbox: WARNING``);
- as root: a private mount namespace with empty tmpfs on /tmp, /var/tmp, /run/lock and /dev/shm
  (the world-writable folders: a build leaves nothing there, and the running loop's shared memory
  is not reachable) and a /proc of its own namespace, then ``PR_SET_NO_NEW_PRIVS``, and drops to the dedicated
  unprivileged user ``xrf-build`` (``build_user.py``); without root the build runs as the
  appliance's own (unprivileged) user;
- runs at nice 19 under ``SCHED_IDLE`` on every CPU except the loop's (``rt_cpu``);
- sets rlimits: address space (memory), processes (fork bombs), file size, CPU seconds, open
  files, no core dumps.

Everything it says goes to the build's log as ``sandbox: ...`` lines.
"""

from __future__ import annotations

import errno
import os
import pwd
import select
import signal
import sys
from collections.abc import Callable
from pathlib import Path

from ..guest import (
    CLONE_NEWIPC,
    CLONE_NEWNET,
    CLONE_NEWNS,
    CLONE_NEWPID,
    CLONE_NEWUSER,
    MS_NODEV,
    MS_NOEXEC,
    MS_NOSUID,
    MS_PRIVATE,
    MS_RDONLY,
    MS_REC,
    MS_REMOUNT,
    PR_SET_NO_NEW_PRIVS,
    PR_SET_PDEATHSIG,
    ROOT_NOT_A_MOUNT,
    bind_fd,
    mount,
    prctl,
    root_is_a_mount,
    unshare,
)
from .sandbox_config import SandboxSpec

# Folders every user may write to: each gets an empty tmpfs in the build's mount namespace.
PRIVATE_TMP = ("/tmp", "/var/tmp", "/run/lock", "/dev/shm")
# Files the build writes: readable by the build user's group (the loop's user may be given it),
# never by others (the data folder's rule, docs/developers/security.md).
BUILD_UMASK = 0o027


def _confine(spec: SandboxSpec) -> list[str]:
    """Private /tmp, /var/tmp, /run/lock and /dev/shm (empty tmpfs), the data folder (``hide``)
    covered too, then put back at the same paths only ``keep``: (path, read_only) — the project's
    source (read-only), its build folder, rt_core's install and the appliance's own code and
    Python (read-only), wherever they were covered (a checkout, venv or data folder under /tmp
    included). Returns the folders made private."""
    private = [t for t in PRIVATE_TMP if os.path.isdir(t)]
    hide = spec.hide
    covered = private + ([hide] if hide else [])
    # O_PATH fds first: once a folder is covered, what was below it cannot be named any more.
    held = [
        (path, os.open(path, os.O_PATH | os.O_CLOEXEC), ro)
        for path, ro in spec.keep
        if os.path.exists(path) and any(Path(path).is_relative_to(c) for c in covered)
    ]
    for target in private:
        mount("tmpfs", target, "tmpfs", MS_NOSUID | MS_NODEV, f"size={spec.limits.tmpfs_mb}m,mode=1777")
    # The folders made on the way must be passable by the build user, whatever the appliance's
    # umask (0o077 for its data files).
    old_umask = os.umask(0o022)
    try:
        if hide:  # its own tmpfs even under a private folder: made read-only below
            os.makedirs(hide, exist_ok=True)
            mount("tmpfs", hide, "tmpfs", MS_NOSUID | MS_NODEV, "size=1m,mode=0755")
        for path, fd, ro in held:
            os.makedirs(path, exist_ok=True)
            bind_fd(fd, path, ro, recursive=True)
            os.close(fd)
    finally:
        os.umask(old_umask)
    if hide:
        # Beside its source and build folder nothing in the data folder is writable, even where
        # the build runs as the appliance's own uid (the owner of that tmpfs).
        mount(None, hide, None, MS_REMOUNT | MS_RDONLY | MS_NOSUID | MS_NODEV)
    return private


def sandbox_main(spec: SandboxSpec, cmd: list[str]) -> int:
    def say(text: str) -> None:
        print(f"sandbox: {text}", flush=True)

    os.setsid()
    root = os.geteuid() == 0
    # network and mounts: own namespaces (without root, inside a user namespace of our own uid)
    mount_ns = False
    try:
        if root:
            unshare(CLONE_NEWNET)
        else:
            ouid, ogid = os.getuid(), os.getgid()
            unshare(CLONE_NEWUSER | CLONE_NEWNET | CLONE_NEWNS)
            Path("/proc/self/setgroups").write_text("deny")
            Path("/proc/self/uid_map").write_text(f"{ouid} {ouid} 1")
            Path("/proc/self/gid_map").write_text(f"{ogid} {ogid} 1")
            mount_ns = True
        say("no network (own network namespace)")
    except OSError as exc:
        say(f"WARNING: could not take the network away ({exc}); building with the host's network")
    if root:
        try:
            unshare(CLONE_NEWNS)
            mount_ns = True
        except OSError as exc:
            say(f"WARNING: no mount namespace ({exc})")
    # Processes: a PID namespace whose init is the build (forked below). The IPC one with it.
    pid_ns = False
    try:
        unshare(CLONE_NEWPID | CLONE_NEWIPC)
        pid_ns = True
    except OSError as exc:
        say(f"WARNING: no PID namespace ({exc}); at the end only processes with this build's token are killed")
    # Open in the sandbox process until it dies: tells the child whether it already did (its
    # getppid() is 0 across the namespace boundary, so it cannot ask that).
    alive_r, alive_w = os.pipe()
    child = os.fork()
    if child:
        os.close(alive_r)
        return _relay(child)
    # The build's first process (PID 1 of its namespace): dies with the sandbox process, so a
    # SIGKILL of the sandbox's group ends the namespace and everything in it.
    os.close(alive_w)
    prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if select.select([alive_r], [], [], 0)[0]:  # EOF: the sandbox died before prctl took hold
        os._exit(137)
    os.close(alive_r)
    try:
        _confined_exec(spec, cmd, say, root, mount_ns, pid_ns)
    except BaseException as exc:  # noqa: BLE001 -- never back into the sandbox's code as a second copy of it
        say(f"error: {exc!r}")
    os._exit(127)


def _relay(child: int) -> int:
    """The sandbox process: wait for the build's first process and exit as it did."""
    while True:
        try:
            _, status = os.waitpid(child, 0)
            break
        except InterruptedError:
            continue
    code = os.waitstatus_to_exitcode(status)
    return 128 - code if code < 0 else code


def _confined_exec(
    spec: SandboxSpec, cmd: list[str], say: Callable[[str], None], root: bool, mount_ns: bool, pid_ns: bool
) -> None:
    import resource

    limits = spec.limits
    try:
        if not mount_ns:
            raise OSError("no mount namespace")
        mount(None, "/", None, MS_REC | MS_PRIVATE, None)
        private = _confine(spec)
        if spec.hide:
            say(f"sees of {spec.hide} only its source (read-only), its build folder and rt_core (read-only)")
        say(f"private {', '.join(private)}")
    except OSError as exc:
        # In a chroot the bare errno ("mount /: Invalid argument") said nothing: say why and the fix.
        why = ROOT_NOT_A_MOUNT if exc.errno == errno.EINVAL and not root_is_a_mount() else str(exc)
        say(f"WARNING: no private {', '.join(PRIVATE_TMP)} and data folder ({why})")
    if pid_ns:
        proc_note = ""
        try:  # a /proc of its own namespace: the build sees its own processes only
            if not mount_ns:
                raise OSError("no mount namespace")
            mount("proc", "/proc", "proc", MS_NOSUID | MS_NODEV | MS_NOEXEC, None)
        except OSError as exc:
            proc_note = f" (the host's /proc stays: {exc})"
        say(f"own PID namespace: every process of the build ends with it{proc_note}")
    # priority and CPUs
    try:
        os.setpriority(os.PRIO_PROCESS, 0, 19)
    except OSError as exc:
        say(f"WARNING: nice 19 refused ({exc})")
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (OSError, AttributeError) as exc:
        say(f"WARNING: SCHED_IDLE refused ({exc}); nice 19 only")
    rt_cpu = limits.rt_cpu
    cpus = os.sched_getaffinity(0)
    if rt_cpu is not None and rt_cpu in cpus:
        rest = cpus - {rt_cpu}
        if rest:
            os.sched_setaffinity(0, rest)
        else:
            say(f"WARNING: CPU {rt_cpu} is the only CPU; the build shares it with the loop at SCHED_IDLE")
    say(f"CPUs {sorted(os.sched_getaffinity(0))} (loop CPU {rt_cpu}), nice 19, SCHED_IDLE")
    # limits
    mb = 1 << 20
    rlimits = [
        (resource.RLIMIT_AS, limits.memory_mb * mb),
        (resource.RLIMIT_NPROC, limits.nproc),
        (resource.RLIMIT_FSIZE, limits.fsize_mb * mb),
        (resource.RLIMIT_CPU, limits.cpu_s),
        (resource.RLIMIT_NOFILE, limits.nofile),
        (resource.RLIMIT_CORE, 0),
    ]
    for which, value in rlimits:
        try:
            resource.setrlimit(which, (value, value))
        except (ValueError, OSError) as exc:
            say(f"WARNING: limit {which} not set ({exc})")
    # user
    if root:
        prctl(PR_SET_NO_NEW_PRIVS, 1)
        os.setgroups([])
        os.setgid(spec.gid)
        os.setuid(spec.uid)
    os.umask(BUILD_UMASK)
    say(
        f"user {pwd.getpwuid(os.getuid()).pw_name} (uid {os.getuid()}), memory {limits.memory_mb} MB/process, "
        f"{limits.nproc} processes, files up to {limits.fsize_mb} MB, wall time {limits.timeout_s:.0f} s"
    )
    sys.stdout.flush()
    os.execvpe(cmd[0], cmd, spec.env)
