"""The run sandbox: every loop process the appliance starts is a guest.

A student's controller is untrusted code that needs firm real time and nothing else. The
appliance never executes it directly: it starts this module (the *launcher*, trusted), which
builds a confinement and only then execs the controller inside it::

    appliance ──spawn──▶ launcher (host PID namespace; holds /dev/cpu_dma_latency; forwards signals)
                            └─fork─▶ init = PID 1 of a new PID namespace (sets up the confinement)
                                        └─fork─▶ PID 2 ──exec──▶ controller

The init (``_init``) stays: a controller that were PID 1 could not raise a signal on itself
(the kernel drops those for a namespace's init), it reaps what the controller forks, and it hands
the controller's wait status back to the launcher, which mirrors it.

Layers (each reported by name; ``LAYERS``):

- ``user``: a uid that is neither root nor the appliance's. As root: the system user ``xrf-run``
  (created on first use). Not root: a user namespace whose uid 1 maps to the first subordinate
  id of the appliance's user (``/etc/subuid``, written with the setuid ``newuidmap``); on a Pi
  deploy/ makes that id ``xrf-loop``. Without subordinate ids the loop keeps the appliance's uid
  (layer missing) but still has no capability anywhere.
- ``no_new_privs`` and ``capabilities``: ``PR_SET_NO_NEW_PRIVS``, empty bounding set (root mode),
  no capability after exec. Real time needs none: the launcher raises ``RLIMIT_RTPRIO`` and
  ``RLIMIT_MEMLOCK`` (root mode; otherwise they come from the service's limits) so the loop may
  use SCHED_FIFO and mlockall as an ordinary user; its CPU pinning is a plain syscall.
- ``mount``: a new root built from an allow-list (a read-only tmpfs): /usr and the library
  folders read-only, a few files of /etc, a /dev with null/zero/urandom plus the real bench's
  /dev/evl and spidev, its own /proc, empty /tmp and /var/tmp, ``/dev/shm`` = the run's own
  folder of shared memory, the run folder read-write and the build read-only, both at their host
  paths. Nothing else of the host exists in it: not the data folder, the databases, other
  projects, homes, /run or the appliance's code.
- ``pid``: the loop is PID 1 of its own PID namespace; when it ends, the kernel kills every
  process it left (a ``setsid`` sleeper included), and it sees no other process of the host.
- ``network``: its own network namespace with a downed loopback: no route anywhere, the
  appliance's port included. ``ipc`` and ``uts`` namespaces likewise.
- ``environment``: built by the appliance from an allow-list (``ENV_ALLOWED``), never a copy.
- ``descriptors``: only 0, 1, 2 reach the controller, and the run's segment (``shm_fd``: a memfd
  the appliance made and sealed at its size, XRF_SHM_FD; the launcher keeps it open too).
- ``limits``: address space, processes, open files, file size, no core dumps; real-time
  priority at most the loop's (``RLIMIT_RTPRIO``: below the safety watcher's) and real-time time
  without blocking (``RLIMIT_RTTIME``: a spinning SCHED_FIFO thread gets SIGXCPU, then SIGKILL).
- ``memory``, ``pids``, ``cpu``: the run's cgroup (server/runs/cgroups.py, made by the appliance): its
  memory with its /dev/shm and /tmp, its processes and threads, the CPUs it may use (the loop's).
  The controller moves itself into it just before its exec (``cgroup_procs``: descriptors the
  launcher opened, so the move is checked against the launcher's credentials), so the bounds hold
  from its first instruction; the init stays outside (spinning threads on the run's CPU cannot
  starve the process that reaps them).
- ``disk``: the run folder is a file system of its own (server/runs/disk.py, mounted by the
  appliance before the launcher starts): nothing to do here but report it.

If a layer cannot be had, the launcher refuses to start the controller unless the appliance
said ``allow_missing`` (the educator's ``--allow-unconfined``); either way it tells the
appliance exactly which layers hold, through a pipe the controller never sees.

This module runs as its own small process: keep its imports to the standard library.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import platform
import resource  # imported now: after the pivot the launcher cannot load extension modules
import shutil
import signal
import stat
import sys
from typing import Any

LAYERS = (
    "user",
    "no_new_privs",
    "capabilities",
    "mount",
    "pid",
    "network",
    "ipc",
    "environment",
    "descriptors",
    "limits",
    "memory",
    "pids",
    "cpu",
    "disk",
)
# The layers the appliance sets up before the launcher starts (the run's cgroup and file
# system): it says in the configuration ("limit_layers") whether each holds.
KERNEL_LIMIT_LAYERS = ("memory", "pids", "cpu", "disk")
# The only variables a controller gets (values chosen by the appliance, never copied from it).
ENV_ALLOWED = frozenset(
    {
        "PATH",
        "LANG",
        "LC_ALL",
        "TZ",
        "HOME",
        "TMPDIR",
        "USER",
        "LOGNAME",
        "XRF_BACKEND",
        "XRF_BUILD_ID",
        "XRF_CPU",
        "XRF_FREQ",
        "XRF_HOST_TIMEOUT_ACTION",
        "XRF_HOST_TIMEOUT_MS",
        "XRF_LOG_DIR",
        "XRF_LOG_TIMING",
        "XRF_LOG_WRITER",
        "XRF_MAX_CYCLES",
        "XRF_PRIO",
        "XRF_PROJECT",
        "XRF_PWM_LIMIT",
        "XRF_QUIET",
        "XRF_RUN_ID",
        "XRF_SHM",
        "XRF_SHM_FD",
        "XRF_SIM",
        "XRF_SIM_FAULTS",
        "XRF_SPI_DEVICE",
        "XRF_SPI_SPEED",
        "XRF_TRANSPORT",
        "XRF_VIRTUAL_TIME",  # a graded run's simulated time (rt_core refuses it on a real board)
    }
)
SHM_NAME = "xrf"  # the channel segment's name inside the sandbox (/dev/shm/xrf)


UNCONFINED_SUFFIX = "-unconfined"


def unconfined_shm_name(shm_dir: str) -> str:
    """The segment's name in the host's /dev/shm when no mount namespace could be had (allowed by
    an educator): beside the run's (then unused) shm folder, named after it."""
    return os.path.basename(shm_dir.rstrip("/")) + UNCONFINED_SUFFIX


REFUSED_EXIT = 126

CLONE_NEWNS = 0x00020000
CLONE_NEWUTS = 0x04000000
CLONE_NEWIPC = 0x08000000
CLONE_NEWUSER = 0x10000000
CLONE_NEWPID = 0x20000000
CLONE_NEWNET = 0x40000000
MS_RDONLY, MS_NOSUID, MS_NODEV, MS_NOEXEC = 1, 2, 4, 8
MS_REMOUNT, MS_BIND, MS_MOVE, MS_REC, MS_PRIVATE = 32, 4096, 8192, 16384, 1 << 18
MNT_DETACH = 2
CAP_SETGID, CAP_SETUID, CAP_SETPCAP, CAP_IPC_LOCK, CAP_SYS_NICE = 6, 7, 8, 14, 23
CAP_NAMES = {CAP_IPC_LOCK: "CAP_IPC_LOCK", CAP_SYS_NICE: "CAP_SYS_NICE"}
PR_SET_KEEPCAPS, PR_CAP_AMBIENT, PR_CAP_AMBIENT_RAISE = 8, 47, 2
PR_SET_PDEATHSIG, PR_CAPBSET_DROP, PR_SET_NO_NEW_PRIVS, PR_GET_NO_NEW_PRIVS = 1, 24, 38, 39
SYS_PIVOT_ROOT = {"x86_64": 155, "aarch64": 41, "riscv64": 41, "armv7l": 218, "armv6l": 218, "i686": 217}
# Read-only from the host, when present: programs and libraries (a controller links libstdc++).
SYSTEM_DIRS = ("/usr", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32")
ETC_FILES = ("/etc/ld.so.cache", "/etc/ld.so.conf", "/etc/ld.so.conf.d", "/etc/localtime", "/etc/nsswitch.conf")
DEV_NODES = ("/dev/null", "/dev/zero", "/dev/full", "/dev/random", "/dev/urandom")
# libevl and glibc read a few sysfs folders (CPU count, the EVL core's devices); read-only.
SYS_DIRS = ("/sys/devices/system/cpu", "/sys/devices/virtual/evl", "/sys/class/evl")


class GuestError(Exception):
    pass


# Why the sandbox refuses to start where / is not a mount point (issue 30: an appliance in a
# chroot, e.g. an arm64 Debian root under qemu-user). Binding / onto itself from in here would
# make it one, but the bind lands on the mount that holds the chroot's folder: a mount this
# process cannot name (it is outside its root) and so cannot make private first, and wherever
# that mount is shared (systemd makes / shared) the bind would propagate into the host's
# namespace, one more stacked mount per run. Whoever made the chroot can do it once, safely.
ROOT_NOT_A_MOUNT = (
    "/ is not a mount point (the appliance runs in a chroot), so the sandbox can neither make "
    "its mounts private nor pivot_root away from it. Bind the chroot's folder onto itself before "
    "entering it: mount --bind DIR DIR && mount --make-rprivate DIR (a container's root is such a "
    "mount already)"
)


def root_is_a_mount() -> bool:
    """Whether / is the root of a mount. In a chroot, mountinfo lists only the mounts below the
    process's root: the one holding its folder is not among them, so no line says "/"."""
    try:
        with open("/proc/self/mountinfo") as f:
            return any(line.split()[4] == "/" for line in f if len(line.split()) > 4)
    except OSError:
        return True  # no /proc: say nothing we cannot know; the mount error stands


_libc = ctypes.CDLL(None, use_errno=True)


def _thread_count() -> int:
    """This process's threads (0 when /proc cannot say)."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 0


def _check(rc: int, what: str) -> None:
    if rc != 0:
        e = ctypes.get_errno()
        raise OSError(e, f"{what}: {os.strerror(e)}")


def _enc(s: str | None) -> bytes | None:
    return s.encode() if s is not None else None


# The namespace primitives, shared with the build sandbox (projects/sandbox.py).


def mount(src: str | None, target: str, fstype: str | None, flags: int, data: str | None = None) -> None:
    _check(_libc.mount(_enc(src), _enc(target), _enc(fstype), ctypes.c_ulong(flags), _enc(data)), f"mount {target}")


def unshare(flags: int) -> None:
    _check(_libc.unshare(ctypes.c_int(flags)), "unshare")


def prctl(option: int, arg: int) -> int:
    return int(
        _libc.prctl(ctypes.c_int(option), ctypes.c_ulong(arg), ctypes.c_ulong(0), ctypes.c_ulong(0), ctypes.c_ulong(0))
    )


def _pivot_root(new_root: str) -> None:
    """pivot_root(".", ".") then detach the old root: nothing of the host stays reachable."""
    os.chdir(new_root)
    number = SYS_PIVOT_ROOT.get(platform.machine())
    if number is None:
        raise OSError(errno.ENOSYS, f"pivot_root: unknown syscall number on {platform.machine()}")
    _check(_libc.syscall(ctypes.c_long(number), b".", b"."), "pivot_root")
    _check(_libc.umount2(b".", ctypes.c_int(MNT_DETACH)), "umount old root")
    os.chdir("/")


def remount_read_only(target: str) -> None:
    """Make the bind mount at ``target`` read-only. A remount must keep the flags the source
    mount has (the kernel locks them in a user namespace): nosuid/nodev/noexec are carried over."""
    st = os.statvfs(target)
    flags = MS_REMOUNT | MS_BIND | MS_RDONLY
    flags |= MS_NOSUID if st.f_flag & os.ST_NOSUID else 0
    flags |= MS_NODEV if st.f_flag & os.ST_NODEV else 0
    flags |= MS_NOEXEC if st.f_flag & os.ST_NOEXEC else 0
    mount(None, target, None, flags)


def bind_fd(src_fd: int, target: str, read_only: bool, recursive: bool = False) -> None:
    """Bind what ``src_fd`` (an O_PATH fd opened before anything was covered, in this mount
    namespace) names onto ``target``."""
    mount(f"/proc/self/fd/{src_fd}", target, None, MS_BIND | (MS_REC if recursive else 0))
    if read_only:
        remount_read_only(target)


def _make_target(path: str, like_dir: bool) -> None:
    os.makedirs(os.path.dirname(path) or "/", exist_ok=True)
    if like_dir:
        os.makedirs(path, exist_ok=True)
    elif not os.path.exists(path):
        with open(path, "w"):
            pass


# ---- the launcher (runs as its own process) ------------------------------------------------------


class _Launch:
    def __init__(self, cfg: dict[str, Any]) -> None:
        self.cfg = cfg
        self.layers: dict[str, str] = {}  # layer -> "" (holds) or why it does not
        self.notes: list[str] = []
        self.mode = cfg["mode"]  # root | userns
        self.src: dict[str, int] = {}
        self.dma_fd = -1
        self.loop_ids: tuple[int, int, list[int]] = (0, 0, [])  # userns mode: (uid, gid, groups) inside
        self.ambient: list[int] = []  # capabilities the controller keeps (plan_realtime)
        self.cgroup_fds: list[int] = []  # the run cgroup's cgroup.procs files (open_cgroups)

    def missing(self, layer: str, why: str) -> None:
        self.layers[layer] = why

    def ok(self, layer: str) -> None:
        self.layers.setdefault(layer, "")

    # -- in the launcher, before the fork ---------------------------------------------------------

    def open_sources(self) -> None:
        try:
            os.close(os.open(self.cfg["exe"], os.O_RDONLY | os.O_CLOEXEC))
        except OSError as exc:
            raise GuestError(f"cannot read the controller {self.cfg['exe']}: {exc.strerror}") from exc
        self._open_sources()

    def _open_sources(self) -> None:
        """O_PATH fds to everything the new root shows, before any mount can hide it (a checkout or
        data folder under /tmp, say, which the staging tmpfs covers)."""
        cfg = self.cfg
        wanted = [
            *SYSTEM_DIRS,
            *ETC_FILES,
            *DEV_NODES,
            *SYS_DIRS,
            cfg["exe"],
            cfg["run_dir"],
            cfg["shm_dir"],
            *cfg.get("read_only", []),
            *cfg.get("devices", []),
        ]
        for path in wanted:
            if path in self.src:
                continue
            try:
                self.src[path] = os.open(path, os.O_PATH | os.O_CLOEXEC | os.O_NOFOLLOW)
            except OSError:
                continue

    def open_cgroups(self) -> None:
        """The run's cgroup.procs files, opened now, before any namespace: the kernel checks a
        move against the credentials of the process that opened the file (Linux 5.16+), so the
        controller can move itself in after it dropped every privilege."""
        for path in self.cfg.get("cgroup_procs", []):
            try:
                self.cgroup_fds.append(os.open(path, os.O_WRONLY | os.O_CLOEXEC))
            except OSError as exc:
                raise GuestError(f"cannot open the run's cgroup {path}: {exc.strerror}") from exc

    def join_cgroups(self) -> None:
        """Move this process (the controller, about to exec) into the run's cgroup."""
        for fd in self.cgroup_fds:
            os.write(fd, b"0")  # "0": the writer itself, whatever its pid in its namespace
            os.close(fd)
        self.cgroup_fds = []

    def hold_dma_latency(self) -> None:
        """The loop's CPUs stay out of deep idle while the run lasts (what cyclictest does): the
        launcher holds the request, so the controller needs no access to the device."""
        try:
            fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY | os.O_CLOEXEC)
            os.write(fd, (0).to_bytes(4, "little"))
            self.dma_fd = fd
        except OSError as exc:
            self.notes.append(f"/dev/cpu_dma_latency not held ({exc.strerror})")

    def enter_namespaces(self) -> None:
        flags = CLONE_NEWNS | CLONE_NEWPID | CLONE_NEWNET | CLONE_NEWIPC | CLONE_NEWUTS
        if self.mode == "userns":
            self._enter_userns(flags)
        else:
            try:
                unshare(flags)
            except OSError as exc:
                for layer in ("mount", "pid", "network", "ipc"):
                    self.missing(layer, f"unshare refused ({exc.strerror})")
                return
        for layer in ("mount", "pid", "network", "ipc"):
            self.ok(layer)

    def _enter_userns(self, flags: int) -> None:
        cfg = self.cfg
        uid, gid = os.getuid(), os.getgid()
        sub_uid, sub_gid = cfg.get("sub_uid"), cfg.get("sub_gid")
        helper = None
        if sub_uid and sub_gid:
            # newuidmap must write our maps from outside the new namespace: a child started
            # before the unshare does it once we are in (it waits on a pipe).
            r, w = os.pipe()
            pid = os.fork()
            if pid == 0:
                os.close(w)
                if not os.read(r, 1):  # the launcher gave up before its unshare
                    os._exit(1)
                parent = os.getppid()
                a = os.spawnvp(
                    os.P_WAIT, "newuidmap", ["newuidmap", str(parent), "0", str(uid), "1", "1", str(sub_uid), "1"]
                )
                b = os.spawnvp(
                    os.P_WAIT,
                    "newgidmap",
                    [
                        "newgidmap",
                        str(parent),
                        "0",
                        str(gid),
                        "1",
                        "1",
                        str(sub_gid),
                        "1",
                        *[x for i, g in enumerate(cfg.get("device_gids", [])) for x in (str(2 + i), str(g), "1")],
                    ],
                )
                os._exit(0 if a == 0 and b == 0 else 1)
            os.close(r)
            helper = (pid, w)
        try:
            unshare(CLONE_NEWUSER | flags)
        except OSError as exc:
            if helper:
                os.close(helper[1])
                os.waitpid(helper[0], 0)
            why = exc.strerror
            threads = _thread_count()
            if exc.errno == errno.EINVAL and threads > 1:
                # The kernel's rule, not a missing feature: what runs us added a thread before
                # the unshare (qemu-user always does: it has its own helper thread).
                why = (
                    f"{why}: this process has {threads} threads and the kernel gives a new user "
                    "namespace only to a single-threaded one; an emulator such as qemu-user adds a "
                    "thread of its own"
                )
            raise GuestError(f"no user namespace ({why}): the loop cannot be confined without root") from exc
        if helper:
            os.write(helper[1], b"x")
            os.close(helper[1])
            _, status = os.waitpid(helper[0], 0)
            if os.waitstatus_to_exitcode(status) != 0:
                raise GuestError("newuidmap/newgidmap refused the subordinate ids of /etc/subuid, /etc/subgid")
            self.loop_ids = (1, 1, [0, *range(2, 2 + len(cfg.get("device_gids", [])))])
        else:
            with open("/proc/self/setgroups", "w") as f:
                f.write("deny")
            with open("/proc/self/uid_map", "w") as f:
                f.write(f"0 {uid} 1")
            with open("/proc/self/gid_map", "w") as f:
                f.write(f"0 {gid} 1")
            self.loop_ids = (0, 0, [])
            self.missing(
                "user",
                "no subordinate uid for this user (/etc/subuid) or no newuidmap: the loop keeps "
                "the appliance's uid, without any capability",
            )

    def build_root(self) -> str:
        """A read-only tmpfs root holding only the allow-list; returns its path (not yet pivoted)."""
        cfg = self.cfg
        try:
            mount(None, "/", None, MS_REC | MS_PRIVATE)
        except OSError as exc:
            if exc.errno == errno.EINVAL and not root_is_a_mount():
                raise GuestError(ROOT_NOT_A_MOUNT) from exc
            raise
        # Staging: our own tmpfs on /tmp (this namespace only); the sources are held as fds.
        mount("tmpfs", "/tmp", "tmpfs", MS_NOSUID | MS_NODEV, "size=1m,mode=0700")
        root = "/tmp/root"
        os.mkdir(root)
        mount("tmpfs", root, "tmpfs", MS_NOSUID, f"size={cfg.get('root_tmpfs_mb', 64)}m,mode=0755")

        def show(path: str, read_only: bool = True, recursive: bool = False) -> bool:
            fd = self.src.get(path)
            if fd is None:
                return False
            target = root + path
            if stat.S_ISLNK(os.fstat(fd).st_mode):
                os.makedirs(os.path.dirname(target), exist_ok=True)
                os.symlink(os.readlink(path), target)  # usrmerge: /lib -> usr/lib
                return True
            _make_target(target, stat.S_ISDIR(os.fstat(fd).st_mode))
            bind_fd(fd, target, read_only, recursive)
            return True

        for path in (*SYSTEM_DIRS, *ETC_FILES, *SYS_DIRS):
            show(path, recursive=path.startswith("/sys"))
        # /dev: a tmpfs with the harmless nodes, the real bench's devices, and the run's shm folder.
        _make_target(root + "/dev", True)
        mount("tmpfs", root + "/dev", "tmpfs", MS_NOSUID, "size=64k,mode=0755")
        for node in DEV_NODES:
            show(node, read_only=False)
        for link, to in (
            ("fd", "/proc/self/fd"),
            ("stdin", "/proc/self/fd/0"),
            ("stdout", "/proc/self/fd/1"),
            ("stderr", "/proc/self/fd/2"),
        ):
            os.symlink(to, f"{root}/dev/{link}")
        for dev in cfg.get("devices", []):
            if not show(dev, read_only=False, recursive=True):
                self.notes.append(f"device {dev} not present")
        os.mkdir(root + "/dev/shm")
        bind_fd(self.src[cfg["shm_dir"]], root + "/dev/shm", read_only=False)
        for tmp in ("/tmp", "/var/tmp"):
            _make_target(root + tmp, True)
            mount("tmpfs", root + tmp, "tmpfs", MS_NOSUID | MS_NODEV, f"size={cfg.get('tmp_mb', 64)}m,mode=1777")
        os.makedirs(root + "/proc", exist_ok=True)
        # The build (read-only) and the run folder (read-write), at their host paths.
        for path in cfg.get("read_only", []):
            show(path)
        show(cfg["run_dir"], read_only=False)
        # The controller itself: a copy in the new root, so its mode in the build folder (which
        # the loop user may not be allowed to execute) does not matter.
        os.makedirs(root + "/xrf", exist_ok=True)
        exe = f"{root}/xrf/{os.path.basename(cfg['exe'])}"
        with open(f"/proc/self/fd/{self.src[cfg['exe']]}", "rb") as src_f, open(exe, "wb") as dst_f:
            shutil.copyfileobj(src_f, dst_f, 1 << 20)
        os.chmod(exe, 0o555)
        loop_uid, loop_gid, _ = self.loop_identity()
        with open(root + "/etc/passwd", "w") as f:
            f.write(
                f"root:x:0:0::/:/usr/sbin/nologin\nxrf-run:x:{loop_uid}:{loop_gid}::{cfg['run_dir']}:/usr/sbin/nologin\n"
            )
        with open(root + "/etc/group", "w") as f:
            f.write(f"root:x:0:\nxrf-run:x:{loop_gid}:\n")
        with open(root + "/etc/hostname", "w") as f:
            f.write("xrf-run\n")
        return root

    def loop_identity(self) -> tuple[int, int, list[int]]:
        """(uid, gid, groups) of the controller, as seen inside its namespaces."""
        if self.mode == "root":
            return self.cfg["uid"], self.cfg["gid"], [self.cfg["gid"], *self.cfg.get("device_gids", [])]
        return self.loop_ids

    # -- in the child (PID 1 of the new namespace), then exec ---------------------------------

    def child(self, root: str | None, err_w: int, status_w: int) -> None:
        cfg = self.cfg
        try:
            if root is not None:
                try:
                    mount("proc", root + "/proc", "proc", MS_NOSUID | MS_NODEV | MS_NOEXEC)
                except OSError as exc:
                    # A user namespace may refuse a new proc (a container masking parts of the host's):
                    # the controller then has no /proc at all rather than the host's.
                    self.notes.append(f"no /proc in the sandbox ({exc.strerror})")
                _pivot_root(root)
                mount(None, "/", None, MS_REMOUNT | MS_RDONLY | MS_NOSUID)
            try:
                _libc.sethostname(b"xrf-run", ctypes.c_size_t(7))
            except OSError:
                pass
            os.chdir(cfg["run_dir"])
            self.set_limits()
            os.umask(0o007)  # what the loop writes stays readable by the appliance's group only
            # Descriptors: 0-2, the error and status pipes and the cgroup files (all close-on-exec)
            # and the run's segment only.
            shm_fd = {cfg["shm_fd"]} if cfg.get("shm_fd") is not None else set()
            _close_all_but({err_w, status_w, *self.cgroup_fds, *shm_fd})
            uid, gid, groups = self.loop_identity()
            if self.mode == "root":
                keep = set(self.ambient)
                for cap in range(0, 64):
                    if cap not in keep and prctl(PR_CAPBSET_DROP, cap) != 0:
                        break
                os.setgroups(groups)
                os.setgid(gid)
                if keep:
                    prctl(PR_SET_KEEPCAPS, 1)
                os.setuid(uid)
                if keep:
                    _set_ambient(sorted(keep))
            elif uid != 0:
                os.setgroups(groups)
                os.setgid(gid)
                os.setuid(uid)
            else:
                # No second id to switch to: a nested user namespace in which our uid is not
                # mapped leaves the controller no capability after exec, over anything.
                unshare(CLONE_NEWUSER)
            if prctl(PR_SET_NO_NEW_PRIVS, 1) != 0:
                raise OSError(ctypes.get_errno(), "PR_SET_NO_NEW_PRIVS refused")
            prctl(PR_SET_PDEATHSIG, signal.SIGKILL)  # the launcher gone (SIGKILL): the run ends
            exe = f"/xrf/{os.path.basename(cfg['exe'])}" if root is not None else cfg["exe"]
            argv = [cfg.get("argv0") or os.path.basename(cfg["exe"])]
            if os.getpid() == 1:
                _init(exe, argv, cfg["env"], err_w, status_w, self.cgroup_fds)
            self.join_cgroups()
            os.execve(exe, argv, cfg["env"])
        except BaseException as exc:  # noqa: BLE001 - anything: report it, never run unconfined
            try:
                os.write(err_w, f"{type(exc).__name__}: {exc}".encode()[:4000])
            finally:
                os._exit(REFUSED_EXIT)

    def set_limits(self) -> None:
        cfg = self.cfg
        mb = 1 << 20
        limits = [
            (resource.RLIMIT_AS, cfg["memory_mb"] * mb, cfg["memory_mb"] * mb),
            (resource.RLIMIT_NPROC, cfg["nproc"], cfg["nproc"]),
            (resource.RLIMIT_NOFILE, cfg["nofile"], cfg["nofile"]),
            (resource.RLIMIT_FSIZE, cfg["fsize_mb"] * mb, cfg["fsize_mb"] * mb),
            (resource.RLIMIT_CORE, 0, 0),
        ]
        if cfg.get("rttime_us"):
            # A real-time thread that runs this long without blocking: SIGXCPU (the run ends with
            # `cpu`); at twice this SIGKILL, for a controller that ignores SIGXCPU.
            limits.append((resource.RLIMIT_RTTIME, cfg["rttime_us"], 2 * cfg["rttime_us"]))
        if self.mode != "root":
            # Never above the loop's priority (the service may allow more, LimitRTPRIO=): the
            # safety watcher runs above it. Root mode sets exactly this below.
            limits.append((resource.RLIMIT_RTPRIO, cfg["priority"], cfg["priority"]))
        for which, soft, hard in limits:
            _soft, given = resource.getrlimit(which)
            if given != resource.RLIM_INFINITY:  # never more than we were given
                soft, hard = min(soft, given), min(hard, given)
            resource.setrlimit(which, (soft, hard))
        if self.mode == "root":
            for which, value, _cap in self.realtime_limits():
                if _cap not in self.ambient:
                    resource.setrlimit(which, (value, value))

    def realtime_limits(self) -> list[tuple[int, int, int]]:
        return [
            (resource.RLIMIT_RTPRIO, self.cfg["priority"], CAP_SYS_NICE),
            (resource.RLIMIT_MEMLOCK, self.cfg["memlock_mb"] << 20, CAP_IPC_LOCK),
        ]

    def plan_realtime(self) -> None:
        """Real time without a capability: raised limits let an ordinary user use SCHED_FIFO up to
        the priority and mlockall. Where root itself may not raise limits (no CAP_SYS_RESOURCE,
        e.g. in a container), the loop keeps just CAP_SYS_NICE / CAP_IPC_LOCK instead; in its own
        PID namespace they reach no other process. Not root: the limits come from the service
        (LimitRTPRIO=, LimitMEMLOCK=), as for any process of that user."""
        if self.mode != "root":
            return
        for which, value, cap in self.realtime_limits():
            try:
                resource.setrlimit(which, (value, value))  # the launcher's own: a test, harmless
            except (ValueError, OSError):
                self.ambient.append(cap)
                self.notes.append(f"kept {CAP_NAMES[cap]}: limit {which} cannot be raised here")
                if cap == CAP_SYS_NICE:
                    self.notes.append(
                        "with CAP_SYS_NICE the controller may take any real-time priority, the safety "
                        "watcher's included: only its cpuset keeps it off the watcher's CPUs"
                    )


class _CapHeader(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _CapData(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]


def _set_ambient(caps: list[int]) -> None:
    """After setuid with KEEPCAPS: exactly ``caps`` permitted, inheritable and ambient (they
    survive the exec of a file without capabilities; nothing else does)."""
    mask = sum(1 << c for c in caps)  # all below 32
    header = _CapHeader(0x20080522, 0)
    data = (_CapData * 2)(_CapData(mask, mask, mask), _CapData(0, 0, 0))
    _check(_libc.capset(ctypes.byref(header), data), "capset")
    for cap in caps:
        _check(
            _libc.prctl(
                ctypes.c_int(PR_CAP_AMBIENT),
                ctypes.c_ulong(PR_CAP_AMBIENT_RAISE),
                ctypes.c_ulong(cap),
                ctypes.c_ulong(0),
                ctypes.c_ulong(0),
            ),
            "PR_CAP_AMBIENT_RAISE",
        )


def _status_report(launch: _Launch, error: str = "") -> dict[str, Any]:
    layers = {name: launch.layers.get(name, "") for name in LAYERS}
    return {
        "mode": launch.mode,
        "layers": layers,
        "missing": {k: v for k, v in layers.items() if v},
        "notes": launch.notes,
        "error": error,
    }


FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2)


def _close_all_but(keep: set[int]) -> None:
    """Close every descriptor from 3 up except `keep`."""
    low = 3
    for fd in sorted(keep):
        os.closerange(low, fd)
        low = fd + 1
    os.closerange(low, 1 << 20)


def _init(exe: str, argv: list[str], env: dict[str, str], err_w: int, status_w: int, cgroup_fds: list[int]) -> None:
    """PID 1 of the run's namespace: a small init, the controller its only child.

    A controller that were PID 1 itself would not die of its own raise(SIGSEGV), and abort()
    would end it by SIGSEGV instead of SIGABRT: the kernel drops a signal sent to a namespace's
    PID 1 from inside unless it has a handler. As PID 2 it behaves as on XRF2. The init forwards
    the launcher's signals, reaps whatever the controller forks (its exit kills them all), and
    hands the controller's wait status to the launcher over `status_w` (its own exit code cannot
    carry a signal: PID 1 cannot kill itself). Returns only in the child, which then execs."""
    child = [0]

    def forward(sig: int, _frame: Any) -> None:
        if child[0] > 0:
            with contextlib.suppress(ProcessLookupError):
                os.kill(child[0], sig)

    signal.pthread_sigmask(signal.SIG_BLOCK, FORWARDED)
    for sig in FORWARDED:
        signal.signal(sig, forward)
    pid = os.fork()
    if pid == 0:
        for sig in FORWARDED:
            signal.signal(sig, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, FORWARDED)
        prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        return  # the caller execs (or reports the failure on err_w)
    child[0] = pid
    os.close(err_w)  # the launcher's EOF comes with the controller's exec
    for fd in cgroup_fds:  # the controller moves itself in; the init stays outside
        os.close(fd)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, FORWARDED)
    while True:
        try:
            reaped, status = os.waitpid(-1, 0)
        except ChildProcessError:
            os._exit(REFUSED_EXIT)
        if reaped == pid:
            os.write(status_w, status.to_bytes(4, "little", signed=True))
            os._exit(0)


def _read_proc(proc_fd: int, name: str) -> str:
    fd = os.open(name, os.O_RDONLY | os.O_CLOEXEC, dir_fd=proc_fd)
    try:
        return os.read(fd, 65536).decode()
    finally:
        os.close(fd)


def _controller_host_pid(proc_fd: int, init_pid: int) -> int:
    """The host pid of the controller: the only child of the namespace's init (`init_pid`).
    `proc_fd`: the host's /proc, opened before the child's pivot_root (which also moves the
    launcher's root: they share the mount namespace, and the new root's /proc is the run's)."""
    with contextlib.suppress(OSError, ValueError):
        children = _read_proc(proc_fd, f"{init_pid}/task/{init_pid}/children").split()
        if children:
            return int(children[0])
    for name in os.listdir(proc_fd):  # kernels without CONFIG_PROC_CHILDREN
        if name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                if int(_read_proc(proc_fd, f"{name}/stat").rsplit(")", 1)[1].split()[1]) == init_pid:
                    return int(name)
    return 0


def _mirror_exit(status: int) -> None:
    """Leave the way the controller did: same exit code, or killed by the same signal."""
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        if sig not in (signal.SIGKILL, signal.SIGSTOP):  # those have no handler to reset
            signal.signal(sig, signal.SIG_DFL)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, [sig])
        os.kill(os.getpid(), sig)
        os._exit(128 + sig)
    os._exit(os.waitstatus_to_exitcode(status))


def launch(cfg: dict[str, Any]) -> None:
    report_fd = cfg["report_fd"]
    proc_fd = os.open("/proc", os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)  # the host's, see _controller_host_pid
    L = _Launch(cfg)

    def say(text: str) -> None:
        os.write(1, f"sandbox: {text}\n".encode())

    def refuse(message: str) -> None:
        say(f"REFUSED: {message}")
        os.write(report_fd, (json.dumps(_status_report(L, message)) + "\n").encode())
        os._exit(REFUSED_EXIT)

    root: str | None = None
    os.umask(0o022)  # the sandbox's own folders (/xrf, /etc, ...) must be passable by the loop user
    try:
        L.open_cgroups()
        L.hold_dma_latency()
        L.enter_namespaces()
        # After the unshare: a bind mount's source must be a mount of our own namespace.
        L.open_sources()
        if not L.layers.get("mount"):
            root = L.build_root()
    except (OSError, GuestError) as exc:
        refuse(str(exc))
    except Exception as exc:  # noqa: BLE001 - a launcher bug must still end in a clear refusal
        refuse(f"sandbox set-up failed: {type(exc).__name__}: {exc}")
    if L.layers.get("mount"):
        # No own /dev/shm: the segment lives in the host's, under the run's own name.
        cfg["env"]["XRF_SHM"] = unconfined_shm_name(cfg["shm_dir"])
    for layer in filter(None, cfg.get("test_drop", "").split(",")):  # TEST ONLY (guest_spawn.TEST_DROP_ENV)
        L.missing(layer, "skipped for a test")
    for layer, why in cfg.get("limit_layers", {}).items():  # the appliance's (KERNEL_LIMIT_LAYERS)
        if layer in KERNEL_LIMIT_LAYERS and why:
            L.missing(layer, why)
        elif layer in KERNEL_LIMIT_LAYERS:
            L.ok(layer)
    for layer in KERNEL_LIMIT_LAYERS:
        if layer not in cfg.get("limit_layers", {}):
            L.missing(layer, "not set up by the appliance")
    L.notes.extend(cfg.get("limit_notes", []))
    L.ok("user")
    for layer in ("no_new_privs", "capabilities", "environment", "descriptors", "limits"):
        L.ok(layer)
    missing = {k: v for k, v in L.layers.items() if v and k in LAYERS}
    if missing and not cfg.get("allow_missing"):
        refuse(
            "missing protection: "
            + "; ".join(f"{k}: {v}" for k, v in missing.items())
            + " (an educator may allow this with xrf serve --allow-unconfined)"
        )
    L.plan_realtime()
    status_r, status_w = os.pipe2(os.O_CLOEXEC)
    err_r, err_w = os.pipe2(os.O_CLOEXEC)
    # Signals that arrive before the child exists are forwarded once it does.
    pending: list[int] = []
    child_pid = 0

    def forward(sig: int, _frame: Any) -> None:
        if child_pid > 0:
            try:
                os.kill(child_pid, sig)
            except ProcessLookupError:
                pass
        else:
            pending.append(sig)

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2):
        signal.signal(sig, forward)
    pid = os.fork()
    if pid == 0:
        os.close(err_r)
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2):
            signal.signal(sig, signal.SIG_DFL)
        os.close(status_r)
        L.child(root, err_w, status_w)
        os._exit(REFUSED_EXIT)
    child_pid = pid
    os.close(err_w)
    os.close(status_w)
    failure = b""
    while chunk := os.read(err_r, 4096):  # EOF at the controller's exec (close-on-exec)
        failure += chunk
    os.close(err_r)
    if failure:
        os.waitpid(pid, 0)
        refuse(f"could not start the controller in its sandbox: {failure.decode(errors='replace')}")
    missing_text = ", ".join(sorted(k for k, v in L.layers.items() if v and k in LAYERS))
    say(
        f"controller started as uid {L.loop_identity()[0]} (in its namespaces); "
        + (f"MISSING: {missing_text}" if missing_text else "all layers hold")
        + "".join(f"; {n}" for n in L.notes)
    )
    # With its own PID namespace the controller is the init's child (_init); else our child.
    controller = (_controller_host_pid(proc_fd, pid) or pid) if not L.layers.get("pid") else pid
    os.close(proc_fd)
    os.write(report_fd, (json.dumps(_status_report(L) | {"pid": controller}) + "\n").encode())
    os.close(report_fd)
    for early in pending:
        forward(early, None)
    while True:
        try:
            _, status = os.waitpid(pid, 0)
            break
        except ChildProcessError:
            status = 0
            break
    # The init hands over the controller's own wait status; without one (no init: no PID
    # namespace, or the init was killed) the child's status is the controller's.
    handed = os.read(status_r, 4)
    os.close(status_r)
    if len(handed) == 4:
        status = int.from_bytes(handed, "little", signed=True)
    _mirror_exit(status)


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m xrflab.guest CONFIG_JSON (started by the appliance)", file=sys.stderr)
        return 2
    launch(json.loads(argv[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
