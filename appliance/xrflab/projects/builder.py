"""The build queue and the sandbox a student's build runs in.

One worker thread takes builds from a FIFO queue, one at a time (the loop's CPU is never
starved by parallel builds). Each build runs ``xrflab.build`` on the project's unpacked source
in a fresh build folder, inside a sandbox started by this module itself
(``python -m xrflab.projects.builder --sandbox CONFIG -- CMD``), which, before exec'ing the build:

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
  unprivileged user ``xrf-build`` (created with ``useradd --system`` on first use); without
  root the build runs as the appliance's own (unprivileged) user;
- runs at nice 19 under ``SCHED_IDLE`` on every CPU except the loop's (``rt_cpu``);
- sets rlimits: address space (memory), processes (fork bombs), file size, CPU seconds, open
  files, no core dumps.

The appliance enforces the wall time: at the limit (and at the end of every build) it kills the
sandbox's process group, which takes the PID namespace with it; where the kernel refused a PID
namespace, it kills every process that carries this build's token in its environment
(``XRF_BUILD_TOKEN``, random per build), never all processes of the build user.
"""

from __future__ import annotations

import hashlib
import json
import os
import pwd
import queue
import re
import secrets
import select
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

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
    bind_fd,
    mount,
    prctl,
    unshare,
)
from ..tied import popen_tied
from .store import BuildRow, ProjectRow, ProjectStore

Publish = Callable[[str, dict[str, Any]], None]
APPLIANCE_DIR = Path(__file__).resolve().parents[2]  # appliance/ (the xrflab package's parent)
LOG_MAX_BYTES = 4 << 20
STREAM_MAX_LINES = 4000
RESULT_FILE = "xrf-result.json"

# Folders every user may write to: each gets an empty tmpfs in the build's mount namespace.
PRIVATE_TMP = ("/tmp", "/var/tmp", "/run/lock", "/dev/shm")
TOKEN_ENV = "XRF_BUILD_TOKEN"
# Files the build writes: readable by the build user's group (the loop's user may be given it),
# never by others (the data folder's rule, docs/developers/security.md).
BUILD_UMASK = 0o027


@dataclass(frozen=True)
class SandboxConfig:
    timeout_s: float = 300.0
    memory_mb: int = 2048  # RLIMIT_AS of each process (cc1plus of a big file needs ~1 GB)
    nproc: int = 256  # RLIMIT_NPROC of the build user
    fsize_mb: int = 512  # RLIMIT_FSIZE: largest file a build may write
    cpu_s: int = 900  # RLIMIT_CPU per process
    nofile: int = 1024
    user: str = "xrf-build"
    rt_cpu: int | None = 1  # the loop's CPU; builds never run there
    tmpfs_mb: int = 256

    @staticmethod
    def from_settings(settings: Any) -> SandboxConfig:
        """Settings attributes ``build_*`` (when the appliance has them), then XRF_BUILD_* env."""
        base = SandboxConfig()
        values: dict[str, Any] = {}
        for f in ("timeout_s", "memory_mb", "nproc", "fsize_mb", "cpu_s", "nofile", "user"):
            v = getattr(settings, "build_" + f, None)
            env = os.environ.get("XRF_BUILD_" + f.upper())
            if env is not None:
                v = type(getattr(base, f))(env)
            if v is not None:
                values[f] = v
        cpu = getattr(settings, "loop_cpu", None)
        if cpu is None:
            cpu = (getattr(settings, "loop_env", {}) or {}).get("XRF_CPU") or os.environ.get("XRF_CPU")
        if cpu not in (None, ""):
            values["rt_cpu"] = int(cpu)
        return SandboxConfig(**{**asdict(base), **values})


# ---- the sandbox (runs in the child, as root or as the appliance's user, then execs) -------------


def _confine(config: dict[str, Any]) -> list[str]:
    """Private /tmp, /var/tmp, /run/lock and /dev/shm (empty tmpfs), the data folder (``hide``)
    covered too, then put back at the same paths only ``keep``: (path, read_only) — the project's
    source (read-only), its build folder, rt_core's install and the appliance's own code and
    Python (read-only), wherever they were covered (a checkout, venv or data folder under /tmp
    included). Returns the folders made private."""
    private = [t for t in PRIVATE_TMP if os.path.isdir(t)]
    hide = config.get("hide")
    covered = private + ([hide] if hide else [])
    # O_PATH fds first: once a folder is covered, what was below it cannot be named any more.
    held = [
        (path, os.open(path, os.O_PATH | os.O_CLOEXEC), ro)
        for path, ro in config.get("keep", [])
        if os.path.exists(path) and any(Path(path).is_relative_to(c) for c in covered)
    ]
    for target in private:
        mount("tmpfs", target, "tmpfs", MS_NOSUID | MS_NODEV, f"size={config['tmpfs_mb']}m,mode=1777")
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


def _sandbox_main(config: dict[str, Any], cmd: list[str]) -> int:
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
        _confined_exec(config, cmd, say, root, mount_ns, pid_ns)
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
    config: dict[str, Any], cmd: list[str], say: Callable[[str], None], root: bool, mount_ns: bool, pid_ns: bool
) -> None:
    import resource

    uid, gid = config["uid"], config["gid"]
    try:
        if not mount_ns:
            raise OSError("no mount namespace")
        mount(None, "/", None, MS_REC | MS_PRIVATE, None)
        private = _confine(config)
        if config.get("hide"):
            say(f"sees of {config['hide']} only its source (read-only), its build folder and rt_core (read-only)")
        say(f"private {', '.join(private)}")
    except OSError as exc:
        say(f"WARNING: no private {', '.join(PRIVATE_TMP)} and data folder ({exc})")
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
    rt_cpu = config.get("rt_cpu")
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
    limits = [
        (resource.RLIMIT_AS, config["memory_mb"] * mb),
        (resource.RLIMIT_NPROC, config["nproc"]),
        (resource.RLIMIT_FSIZE, config["fsize_mb"] * mb),
        (resource.RLIMIT_CPU, config["cpu_s"]),
        (resource.RLIMIT_NOFILE, config["nofile"]),
        (resource.RLIMIT_CORE, 0),
    ]
    for which, value in limits:
        try:
            resource.setrlimit(which, (value, value))
        except (ValueError, OSError) as exc:
            say(f"WARNING: limit {which} not set ({exc})")
    # user
    if root:
        prctl(PR_SET_NO_NEW_PRIVS, 1)
        os.setgroups([])
        os.setgid(gid)
        os.setuid(uid)
    os.umask(BUILD_UMASK)
    say(
        f"user {pwd.getpwuid(os.getuid()).pw_name} (uid {os.getuid()}), memory {config['memory_mb']} MB/process, "
        f"{config['nproc']} processes, files up to {config['fsize_mb']} MB, wall time {config['timeout_s']:.0f} s"
    )
    sys.stdout.flush()
    os.execvpe(cmd[0], cmd, config["env"])


def _inner_main(src: str, build_dir: str) -> int:
    """Inside the sandbox: the build itself; the result goes to a JSON file in the build folder."""
    from xrflab import build

    out = Path(build_dir) / RESULT_FILE
    try:
        # within=src: the messages are looked for in the uploaded source only (not in the
        # project folder's older versions next to it).
        r = build.build_project(src, Path(build_dir) / "cmake", log=lambda line: print(line, flush=True), within=src)
    except build.BuildError as exc:
        out.write_text(json.dumps({"ok": False, "error": exc.message}))
        print(f"error: {exc.message}", flush=True)
        return 1
    out.write_text(
        json.dumps(
            {
                "ok": True,
                "executable": str(r.executable),
                "layout": r.layout,
                "twenty_sim": r.twenty_sim,
                "taken": r.taken,
                "left_out": r.left_out,
            }
        )
    )
    return 0


# ---- the appliance side -------------------------------------------------------------------------


def ensure_build_user(name: str) -> tuple[int, int, str]:
    """(uid, gid, note). As root: the dedicated user, created if missing. Else: ourselves."""
    if os.geteuid() != 0:
        return os.getuid(), os.getgid(), f"not root: builds run as the appliance's own user (uid {os.getuid()})"
    try:
        pw = pwd.getpwnam(name)
    except KeyError:
        nologin = "/usr/sbin/nologin" if os.path.exists("/usr/sbin/nologin") else "/bin/false"
        r = subprocess.run(
            [
                "useradd",
                "--system",
                "--user-group",
                "--no-create-home",
                "--home-dir",
                "/nonexistent",
                "--shell",
                nologin,
                "--comment",
                "XRF Lab student builds",
                name,
            ],
            capture_output=True,
            text=True,
        )
        if r.returncode != 0 and "already exists" not in r.stderr:
            raise RuntimeError(f"cannot create the build user {name}: {r.stderr.strip()}") from None
        pw = pwd.getpwnam(name)
    if pw.pw_uid == 0:
        raise RuntimeError(f"build user {name} is root")
    return pw.pw_uid, pw.pw_gid, f"root: builds run as {name} (uid {pw.pw_uid})"


def build_processes(token: str) -> list[int]:
    """Pids of the processes that carry ``token`` (XRF_BUILD_TOKEN) in their environment: one
    build's, whichever appliance or user started them. Reading another user's environ needs root
    (as root builds run as the build user) or the same uid (without root builds run as ours)."""
    needle = f"{TOKEN_ENV}={token}".encode()
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry.name}/environ", "rb") as f:
                env = f.read(1 << 20)
        except OSError:
            continue
        if needle in env.split(b"\0"):
            found.append(int(entry.name))
    return found


def kill_build_processes(token: str, rounds: int = 5) -> None:
    """SIGKILL every process of one build (by its token), again while some keep appearing (a
    fork racing the scan). Only needed where the kernel gave no PID namespace: with one, the
    sandbox's death has ended them all already and this finds nothing."""
    for _ in range(rounds):
        pids = build_processes(token)
        if not pids:
            return
        for pid in pids:
            with _suppress():
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.02)


def _first_line(cmd: list[str]) -> str:
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=10)
        return (r.stdout or r.stderr).splitlines()[0].strip()
    except (OSError, IndexError, subprocess.SubprocessError):
        return f"{cmd[0]}: not found"


_TOOLCHAIN: str | None = None


def toolchain() -> str:
    global _TOOLCHAIN
    if _TOOLCHAIN is None:
        cxx = os.environ.get("CXX") or "c++"
        _TOOLCHAIN = "; ".join([_first_line(["cmake", "--version"]), _first_line([cxx, "--version"])])
    return _TOOLCHAIN


def source_hash(src: Path) -> str:
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in os.walk(src):
        dirnames.sort()
        for f in sorted(filenames):
            p = Path(dirpath) / f
            rel = p.relative_to(src).as_posix()
            h.update(rel.encode() + b"\0")
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 16), b""):
                    h.update(chunk)
            h.update(b"\0")
    return h.hexdigest()[:16]


# ---- diagnostics --------------------------------------------------------------------------------

_DIAG_RE = re.compile(
    r"^(?P<file>[^\s:][^:]*?):(?P<line>\d+):(?:(?P<col>\d+):)?\s*(?P<kind>fatal error|error|warning|note):\s*(?P<msg>.*)$"
)
_CMAKE_RE = re.compile(
    r"^CMake (?P<kind>Error|Warning)(?: \(dev\))? at (?P<file>[^:]+):(?P<line>\d+)(?: \((?P<cmd>[^)]*)\))?:"
)
_MSG_RE = re.compile(r"^(?:.*?error: )?(?P<file>[^\s:]+\.msg):(?P<line>\d+):\s*(?P<msg>.*)$")
_LINK_RE = re.compile(r"(undefined reference to [`'].*?'|multiple definition of [`'].*?'|cannot find -l\S+)")


def parse_diagnostics(lines: list[str], src: Path, build_dir: Path) -> list[dict[str, Any]]:
    """file:line[:col] errors and warnings of the compiler, CMake and the .msg generator."""
    out: list[dict[str, Any]] = []
    seen: set[tuple[Any, ...]] = set()
    src_s, build_s = str(src.resolve()), str(build_dir.resolve())

    def rel(path: str) -> tuple[str, bool]:
        p = path.strip()
        if p.startswith(src_s + "/"):
            return p[len(src_s) + 1 :], True
        if p.startswith(build_s + "/"):
            return "(build) " + p[len(build_s) + 1 :], False
        if not os.path.isabs(p) and not p.startswith(".."):
            return p, (src / p).is_file()
        return p, False

    for i, line in enumerate(lines):
        m = _DIAG_RE.match(line)
        d: dict[str, Any] | None = None
        if m and not line.startswith("$ "):
            f, inside = rel(m.group("file"))
            kind = "error" if m.group("kind") == "fatal error" else m.group("kind")
            d = {
                "file": f,
                "line": int(m.group("line")),
                "col": int(m.group("col")) if m.group("col") else None,
                "kind": kind,
                "message": m.group("msg"),
                "in_project": inside,
                "source": "compiler",
            }
        elif m := _CMAKE_RE.match(line):
            f, inside = rel(m.group("file"))
            msg = next((x.strip() for x in lines[i + 1 : i + 6] if x.strip()), "")
            d = {
                "file": f,
                "line": int(m.group("line")),
                "col": None,
                "kind": m.group("kind").lower(),
                "message": msg,
                "in_project": inside,
                "source": "cmake",
            }
        elif (m := _MSG_RE.match(line)) and ".msg:" in line:
            f, inside = rel(m.group("file"))
            d = {
                "file": f,
                "line": int(m.group("line")),
                "col": None,
                "kind": "error",
                "message": m.group("msg"),
                "in_project": inside,
                "source": "msg",
            }
        elif m := _LINK_RE.search(line):
            d = {
                "file": "",
                "line": None,
                "col": None,
                "kind": "error",
                "message": "link error: " + m.group(1),
                "in_project": False,
                "source": "linker",
            }
            pre = line.split(":(", 1)[0]
            if pre.endswith((".cpp", ".c", ".cc", ".o")) or ":(" in line:
                d["context"] = pre
        if d:
            key = (d["file"], d["line"], d["col"], d["message"])
            if key not in seen:
                seen.add(key)
                d["log_line"] = i
                out.append(d)
    return out


_HINTS = [
    (
        re.compile(r"MemoryError|std::bad_alloc|virtual memory exhausted|Cannot allocate memory|out of memory", re.I),
        "the build ran out of memory (limit {memory_mb} MB per process)",
    ),
    (
        re.compile(r"Resource temporarily unavailable|fork: retry|Cannot fork|can't fork|fork failed", re.I),
        "the build started too many processes (limit {nproc})",
    ),
    (
        re.compile(
            r"Could not resolve host|Couldn't resolve|Network is unreachable|Name or service not known|"
            r"Temporary failure in name resolution|file DOWNLOAD|Couldn't connect",
            re.I,
        ),
        "builds have no network: everything the project needs must be in the project folder",
    ),
    (re.compile(r"File size limit exceeded", re.I), "the build wrote a file over {fsize_mb} MB"),
    (
        re.compile(r"(Permission denied|Read-only file system)", re.I),
        "a build may only write inside its own build folder",
    ),
]


def summarise(
    ok: bool,
    lines: list[str],
    diags: list[dict[str, Any]],
    cfg: SandboxConfig,
    timed_out: bool,
    error: str,
    duration: float,
) -> str:
    if ok:
        return f"built in {duration:.1f} s"
    hint = ""
    text = "\n".join(lines[-400:])
    for rx, msg in _HINTS:
        if rx.search(text):
            hint = msg.format(**asdict(cfg))
            break
    if timed_out:
        return (
            f"the build took longer than {cfg.timeout_s:.0f} s and was stopped (is something in the build "
            "waiting or looping?)" + (f" — {hint}" if hint else "")
        )
    first = next((d for d in diags if d["kind"] == "error"), None)
    if first and first["source"] == "linker":
        head = first["message"] + (f" (in {first['context']})" if first.get("context") else "")
    elif first:
        loc = f"{first['file']}:{first['line']}" + (f":{first['col']}" if first.get("col") else "")
        head = f"{loc}: {first['kind']}: {first['message']}"
    else:
        head = error or "the build failed"
    return f"{head} — {hint}" if hint and hint not in head else head


# ---- the queue ----------------------------------------------------------------------------------


@dataclass
class _Job:
    build: BuildRow
    project: ProjectRow
    src: Path


@dataclass
class Builder:
    store: ProjectStore
    projects_root: Path
    publish: Publish
    config: SandboxConfig = field(default_factory=SandboxConfig)
    # Covered in the build's mount namespace except for what the build needs (the data folder).
    hide_dir: Path | None = None

    def __post_init__(self) -> None:
        self._queue: queue.Queue[_Job | None] = queue.Queue()
        self._pending: list[int] = []
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.current: int | None = None
        self._user: tuple[int, int, str] | None = None
        self._procs: dict[int, tuple[subprocess.Popen[str], str]] = {}  # pid -> (sandbox, build token)
        self.on_done: list[Callable[[BuildRow], None]] = []

    # -- public ---------------------------------------------------------------------------------

    def submit(self, project: ProjectRow, src: Path) -> tuple[BuildRow, bool]:
        """Queue a build of the project's current source; (build, reused). An unchanged source
        (same hash, same toolchain) that built before is not built again: that build is returned."""
        digest = source_hash(src)
        tc = self.toolchain_id()
        old = self.store.reusable(project.id, digest, tc)
        if old is not None:
            return old, True
        row = self.store.create_build(project, digest, tc)
        with self._lock:
            self._pending.append(row.id)
            self._start()
        self._queue.put(_Job(row, project, src))
        self._announce(row, "queued", position=self.position(row.id))
        return row, False

    def position(self, build_id: int) -> int:
        with self._lock:
            ids = ([self.current] if self.current else []) + self._pending
        return ids.index(build_id) if build_id in ids else -1

    def toolchain_id(self) -> str:
        from .. import build

        digest = build._content_hash([build.REPO_ROOT / "rt_core", build.REPO_ROOT / "appliance/xrflab/msgdef.py"])
        return f"{toolchain()}; rt_core {digest}"

    def stop(self) -> None:
        with self._lock:
            procs = list(self._procs.values())
        self._queue.put(None)
        for p, token in procs:  # this builder's builds only: another appliance's go on
            with _suppress():
                os.killpg(p.pid, signal.SIGKILL)
            kill_build_processes(token)

    # -- worker ---------------------------------------------------------------------------------

    def _start(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._work, name="xrf-project-builds", daemon=True)
            self._thread.start()

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            with self._lock:
                if job.build.id in self._pending:
                    self._pending.remove(job.build.id)
                self.current = job.build.id
            try:
                row = self._build(job)
            except Exception as exc:  # anything unexpected still ends the build visibly
                row = self.store.update_build(
                    job.build.id, status="failed", ended=time.time(), result=f"internal error: {exc!r}"
                )
                self._announce(row, "failed")
            finally:
                with self._lock:
                    self.current = None
            for cb in self.on_done:
                with _suppress():
                    cb(row)

    def _announce(self, row: BuildRow, status: str, **extra: Any) -> None:
        self.publish(
            "build",
            {
                "build_id": row.id,
                "project_id": row.project_id,
                "owner": row.owner,
                "status": status,
                "result": row.result,
                **extra,
            },
        )

    def _build(self, job: _Job) -> BuildRow:
        from .. import build

        cfg = self.config
        project_dir = job.src.parent
        build_dir = project_dir / "builds" / str(job.build.id)
        log_path = build_dir.with_suffix(".log")
        build_dir.mkdir(parents=True, exist_ok=False)
        t0 = time.monotonic()
        row = self.store.update_build(job.build.id, status="building", started=time.time(), log_path=str(log_path))
        self._announce(row, "building")
        lines: list[str] = []
        streamed = 0
        log_bytes = 0
        with open(log_path, "w", encoding="utf-8", errors="replace") as logf:

            def log(line: str) -> None:
                nonlocal streamed, log_bytes
                lines.append(line)
                if len(lines) > 20000:
                    del lines[:5000]
                if log_bytes < LOG_MAX_BYTES:
                    logf.write(line + "\n")
                    logf.flush()
                    log_bytes += len(line) + 1
                    if log_bytes >= LOG_MAX_BYTES:
                        logf.write("… log truncated\n")
                if streamed < STREAM_MAX_LINES:
                    streamed += 1
                    self.publish(
                        "build",
                        {
                            "build_id": row.id,
                            "project_id": row.project_id,
                            "owner": row.owner,
                            "line": line if streamed < STREAM_MAX_LINES else "… (more in the build log)",
                        },
                    )

            error = ""
            timed_out = False
            ok = False
            details: dict[str, Any] = {}
            try:
                prefix = build.ensure_rt_core(log)
                uid, gid, note = self._ensure_user()
                log(f"sandbox: {note}")
                cache_dir = self._rt_core_for_user(prefix, uid)
                self._check_reachable(build_dir, uid, gid)
                os.chown(build_dir, uid, gid)
                os.chmod(build_dir, 0o751)  # the build user's; others may only pass (no listing)
                self._share_source(job.src, uid, gid)
                timed_out, rc = self._run_sandboxed(job.src, build_dir, cache_dir, uid, gid, log)
                result = self._read_result(build_dir)
                ok = rc == 0 and not timed_out and bool(result.get("ok"))
                if ok:
                    exe = Path(result["executable"]).resolve()
                    if not exe.is_relative_to(build_dir.resolve()) or not exe.is_file():
                        ok, error = False, "the build's executable is not inside its build folder"
                    else:
                        details["executable_name"] = exe.name
                        row = self.store.update_build(row.id, executable=str(exe))
                        details["layout"] = result.get("layout")
                        details["twenty_sim"] = result.get("twenty_sim")
                else:
                    error = result.get("error", "") or (f"the build failed (exit {rc})" if rc else "")
            except (build.BuildError, RuntimeError, OSError) as exc:
                error = str(exc).splitlines()[0]
                log(f"error: {error}")
            duration = time.monotonic() - t0
            diags = parse_diagnostics(lines, job.src, build_dir)
            details["diagnostics"] = diags[:200]
            details["sandbox"] = asdict(cfg)
            details.update(self._project_facts(job.src))
            if ok and details.get("twenty_sim"):
                freq = details["twenty_sim"].get("frequency_hz")
                if freq:
                    details["cycle_freq"] = freq
            result_text = summarise(ok, lines, diags, cfg, timed_out, error, duration)
            log(("OK: " if ok else "FAILED: ") + result_text)
        row = self.store.update_build(
            row.id,
            status="ok" if ok else "failed",
            ended=time.time(),
            duration=duration,
            result=result_text,
            details=details,
        )
        self._announce(row, row.status, duration=duration)
        return row

    def _project_facts(self, src: Path) -> dict[str, Any]:
        from . import source, twentysim

        located = source.locate(src)
        return {
            "twenty_sim_tokens": twentysim.describe(located.project if located else src),
            "messages": source.message_fields(src, located),
        }

    def _ensure_user(self) -> tuple[int, int, str]:
        if self._user is None:
            self._user = ensure_build_user(self.config.user)
        return self._user

    def _rt_core_for_user(self, prefix: Path, uid: int) -> Path | None:
        """An XRF_CACHE_DIR the build user can read holding rt_core's install (a copy when the
        appliance's own cache is private, e.g. under /root)."""
        if uid == os.getuid():
            return None
        mirror = self.projects_root / ".rt_core"
        target = mirror / "rt_core" / prefix.name
        if not (target / ".xrf-complete").exists():
            tmp = mirror / "rt_core" / f".{prefix.name}.{os.getpid()}.tmp"
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(prefix, tmp, symlinks=True)
            for dirpath, _dirnames, filenames in os.walk(tmp):
                os.chmod(dirpath, 0o755)
                for f in filenames:
                    fp = os.path.join(dirpath, f)
                    if not os.path.islink(fp):
                        os.chmod(fp, os.stat(fp).st_mode | 0o444)
            os.chmod(mirror, 0o755)
            os.chmod(mirror / "rt_core", 0o755)
            try:
                os.rename(tmp, target)
            except OSError:
                shutil.rmtree(tmp, ignore_errors=True)
        return mirror

    def _check_reachable(self, path: Path, uid: int, gid: int) -> None:
        """The build user must pass every folder down to ``path``. Our own folders inside the data
        folder get search permission for others (``o+x``: pass, never list or read; the 0o077
        umask left them without); anything else that blocks it is an error to fix by hand."""
        if uid == os.getuid():
            return
        base = (self.hide_dir or self.projects_root).resolve()
        for parent in [*reversed(path.parents)]:
            st = parent.stat()
            if (
                st.st_mode & 0o001
                or (st.st_uid == uid and st.st_mode & 0o100)
                or (st.st_gid == gid and st.st_mode & 0o010)
            ):
                continue
            if parent.resolve().is_relative_to(base) and st.st_uid == os.getuid():
                os.chmod(parent, stat.S_IMODE(st.st_mode) | 0o001)
                continue
            raise RuntimeError(
                f"the build user cannot reach {parent} (no search permission): put the appliance's "
                "data folder where other users may pass (chmod o+x)"
            )

    def _share_source(self, src: Path, uid: int, gid: int) -> None:
        """The build user reads the project's source through its group (read-only; the source is
        mounted read-only in the sandbox as well), never through 'other' bits: a data-folder file
        is never world-readable. Links are left alone (an archive brings none)."""
        if uid == os.getuid():
            return
        for dirpath, dirnames, filenames in os.walk(src):
            for name in [".", *dirnames, *filenames]:
                path = os.path.join(dirpath, name)
                st = os.lstat(path)
                if stat.S_ISLNK(st.st_mode):
                    continue
                mode = stat.S_IMODE(st.st_mode) & 0o700
                if stat.S_ISDIR(st.st_mode):
                    mode |= 0o050
                else:
                    mode |= 0o040 | (0o010 if mode & 0o100 else 0)
                if st.st_gid != gid:
                    os.chown(path, -1, gid, follow_symlinks=False)
                os.chmod(path, mode)

    def _python_for(self, uid: int) -> str:
        if uid == os.getuid():
            return sys.executable
        for cand in (sys.executable, "/usr/bin/python3", "/usr/local/bin/python3"):
            if _reachable_by_other(Path(cand)):
                return cand
        raise RuntimeError("no Python the build user may run (the appliance's is private): install python3")

    def _run_sandboxed(
        self, src: Path, build_dir: Path, cache_dir: Path | None, uid: int, gid: int, log: Callable[[str], None]
    ) -> tuple[bool, int]:
        cfg = self.config
        token = secrets.token_hex(16)
        env = {
            TOKEN_ENV: token,  # marks this build's processes (kill_build_processes)
            "PATH": "/usr/local/bin:/usr/bin:/bin",
            "HOME": str(build_dir),
            "TMPDIR": "/tmp",
            "LANG": "C.UTF-8",
            "PYTHONPATH": str(APPLIANCE_DIR),
            "PYTHONDONTWRITEBYTECODE": "1",
            "CLICOLOR_FORCE": "0",
        }
        if cache_dir is not None:
            env["XRF_CACHE_DIR"] = str(cache_dir)
        elif os.environ.get("XRF_CACHE_DIR"):
            env["XRF_CACHE_DIR"] = os.environ["XRF_CACHE_DIR"]
        inner = [self._python_for(uid), "-m", "xrflab.projects.builder", "--inner", str(src), str(build_dir)]
        config: dict[str, Any] = {**asdict(cfg), "uid": uid, "gid": gid, "env": env}
        from .. import build

        cache = Path(env.get("XRF_CACHE_DIR") or build._cache_root()).resolve()
        # What the build needs where the sandbox covers a folder (the data folder, /tmp, ...).
        keep = [
            (str(src.resolve()), True),
            (str(build_dir.resolve()), False),
            (str(cache), True),
            (str(APPLIANCE_DIR), True),
            (str(build.REPO_ROOT / "rt_core"), True),
            (str(Path(sys.prefix).resolve()), True),
        ]
        config["keep"] = keep
        hide = self.hide_dir.resolve() if self.hide_dir else None
        if hide is not None and all(Path(k).is_relative_to(hide) for k, _ in keep[:2]):
            config["hide"] = str(hide)
        cmd = [sys.executable, "-m", "xrflab.projects.builder", "--sandbox", json.dumps(config), "--", *inner]
        wenv = {TOKEN_ENV: token, "PATH": env["PATH"], "PYTHONPATH": str(APPLIANCE_DIR), "LANG": "C.UTF-8"}
        # Tied: a build does not run on after the appliance died (server/children.popen_tied).
        proc = popen_tied(
            cmd,
            death_signal=signal.SIGKILL,
            cwd=build_dir,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            errors="replace",
            bufsize=1,
            env=wenv,
        )
        with self._lock:
            self._procs[proc.pid] = (proc, token)

        def pump() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                log(line.rstrip("\n"))

        reader = threading.Thread(target=pump, name="xrf-build-output", daemon=True)
        reader.start()
        timed_out = False
        try:
            rc = proc.wait(timeout=cfg.timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            with _suppress():
                os.killpg(proc.pid, signal.SIGKILL)
            rc = proc.wait()
        finally:
            # Whatever the build left behind (background children, a fork bomb's remains): the
            # group's SIGKILL ends the PID namespace; the token finds them without one. Only
            # this build's: another appliance's build as the same user goes on.
            with _suppress():
                os.killpg(proc.pid, signal.SIGKILL)
            kill_build_processes(token)
            with self._lock:
                self._procs.pop(proc.pid, None)
        reader.join(5)
        if timed_out:
            log(f"sandbox: wall-time limit of {cfg.timeout_s:.0f} s reached: build stopped")
        return timed_out, rc

    def _read_result(self, build_dir: Path) -> dict[str, Any]:
        p = build_dir / RESULT_FILE
        try:
            fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            return {}
        with os.fdopen(fd) as f:
            try:
                data = json.loads(f.read(1 << 20))
            except ValueError:
                return {}
        return data if isinstance(data, dict) else {}


def _reachable_by_other(path: Path) -> bool:
    try:
        real = path.resolve()
        for parent in real.parents:
            if not parent.stat().st_mode & 0o001:
                return False
        return bool(real.stat().st_mode & 0o001)
    except OSError:
        return False


class _suppress:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> bool:
        return exc[0] is not None and issubclass(exc[0], (OSError, ProcessLookupError))  # type: ignore[arg-type]


def main(argv: list[str]) -> int:
    if argv and argv[0] == "--sandbox":
        sep = argv.index("--")
        return _sandbox_main(json.loads(argv[1]), argv[sep + 1 :])
    if argv and argv[0] == "--inner":
        return _inner_main(argv[1], argv[2])
    print(
        "usage: python -m xrflab.projects.builder --sandbox CONFIG -- CMD... | --inner SRC BUILD_DIR", file=sys.stderr
    )
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
