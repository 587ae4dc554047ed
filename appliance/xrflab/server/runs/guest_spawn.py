"""The appliance's side of the run sandbox (``xrflab.guest``): who the controller runs as, what
its sandbox shows, and starting the launcher.

The supervisor asks ``GuestSpawner.spawn()`` for a loop process; it gets back the launcher's
process (its exit is the controller's exit, signals sent to it reach the controller) and the
launcher's report of which protection layers hold. docs/developers/security.md, "The run
sandbox", describes the model.
"""

from __future__ import annotations

import asyncio
import json
import os
import pwd
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ... import guest
from ..settings import Settings
from . import children
from . import limits as run_limits
from .limits import RunLimits

APPLIANCE_DIR = Path(__file__).resolve().parents[3]  # appliance/ (the xrflab package's parent)
DEFAULT_PRIORITY = 80  # rt_core's kDefaultPriority: the loop's SCHED_FIFO priority unless XRF_PRIO
RUN_USER = Settings.run_user
# TEST ONLY: $XRF_GUEST_TEST_DROP=<layer>[,<layer>] makes the launcher report those layers missing
# ("skipped for a test"), as on a machine that cannot have them. Not for "mount" (the channel
# segment's place depends on it). Used by tests/ui; never set it on a bench.
TEST_DROP_ENV = "XRF_GUEST_TEST_DROP"


def dropped_for_a_test() -> str:
    """TEST ONLY: the layers named in $XRF_GUEST_TEST_DROP (known ones, never "mount")."""
    return ",".join(x for x in os.environ.get(TEST_DROP_ENV, "").split(",") if x in guest.LAYERS and x != "mount")


@dataclass(frozen=True)
class GuestLimits:
    memory_mb: int = 1024  # RLIMIT_AS of the controller (the loop itself needs ~60 MB)
    nproc: int = 64  # RLIMIT_NPROC: threads and processes of the loop user
    nofile: int = 256  # RLIMIT_NOFILE
    fsize_mb: int = 512  # RLIMIT_FSIZE: largest file the controller may write
    tmp_mb: int = 64  # its private /tmp and /var/tmp (tmpfs, counted as its memory)
    memlock_mb: int = 512  # RLIMIT_MEMLOCK granted for mlockall (root mode)


@dataclass
class GuestReport:
    """What the launcher said: mode, layer -> "" (holds) or why not, notes, a refusal."""

    mode: str = "none"
    layers: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    error: str = ""
    pid: int = 0  # the controller's pid (host's view); the launcher's exit mirrors its exit

    @property
    def missing(self) -> dict[str, str]:
        return {k: v for k, v in self.layers.items() if v}

    def as_dict(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "layers": self.layers,
            "missing": self.missing,
            "notes": self.notes,
            "confined": not self.missing and self.mode != "none",
        }


def _sub_ranges(path: str, user: pwd.struct_passwd) -> list[tuple[int, int]]:
    """Ranges of /etc/subuid or /etc/subgid that name this user (by name or uid)."""
    out = []
    try:
        lines = Path(path).read_text().splitlines()
    except OSError:
        return []
    for line in lines:
        parts = line.strip().split(":")
        if len(parts) == 3 and parts[0] in (user.pw_name, str(user.pw_uid)):
            try:
                out.append((int(parts[1]), int(parts[2])))
            except ValueError:
                continue
    return out


def _sub_range(path: str, user: pwd.struct_passwd) -> tuple[int, int] | None:
    """The first range of /etc/subuid or /etc/subgid that names this user."""
    ranges = _sub_ranges(path, user)
    return ranges[0] if ranges else None


@dataclass(frozen=True)
class Identity:
    """Who the controller will be. ``mode``: root (setuid to ``user``) or userns."""

    mode: str
    uid: int  # host uid of the controller
    gid: int
    note: str
    sub_uid: int | None = None
    sub_gid: int | None = None


def identity(run_user: str = RUN_USER) -> Identity:
    if os.geteuid() == 0:
        from ...projects.build_user import RUN_USER_COMMENT, ensure_build_user

        uid, gid, _ = ensure_build_user(run_user, RUN_USER_COMMENT)
        return Identity("root", uid, gid, f"controllers run as {run_user} (uid {uid})")
    me = pwd.getpwuid(os.getuid())
    su, sg = _sub_range("/etc/subuid", me), _sub_range("/etc/subgid", me)
    tools = shutil.which("newuidmap") and shutil.which("newgidmap")
    if su and sg and tools:
        return Identity(
            "userns",
            su[0],
            sg[0],
            f"controllers run as subordinate uid {su[0]} of {me.pw_name} (user namespace)",
            su[0],
            sg[0],
        )
    why = (
        "no newuidmap (Debian package uidmap)"
        if not tools
        else f"no /etc/subuid and /etc/subgid range for {me.pw_name}"
    )
    return Identity(
        "userns",
        os.getuid(),
        os.getgid(),
        f"controllers keep uid {os.getuid()} ({why}), in a user namespace without capabilities",
    )


class GuestSpawner:
    def __init__(self, settings: Any) -> None:
        self.settings = settings
        self.limits = GuestLimits()
        self._identity: Identity | None = None

    @property
    def identity(self) -> Identity:
        if self._identity is None:
            self._identity = identity(self.settings.run_user)
        return self._identity

    def devices(self) -> list[str]:
        """What a real bench's controller needs of /dev (EVL core, SPI to the ico board)."""
        out = []
        if self.settings.bench_is_real() or Path("/dev/evl").exists():
            for dev in ("/dev/evl", *self.settings.spi_bench()):
                if Path(dev).exists():
                    out.append(dev)
        return out

    def device_gids(self) -> list[int]:
        gids: set[int] = set()
        for dev in self.devices():
            p = Path(dev)
            with_children = [p, *p.rglob("*")] if p.is_dir() else [p]
            for q in with_children:
                try:
                    g = q.stat().st_gid
                except OSError:
                    continue
                if g != 0:
                    gids.add(g)
        ident = self.identity
        if ident.mode == "userns":
            # Only groups the appliance's user may map (deploy/ lists them in /etc/subgid).
            me = pwd.getpwuid(os.getuid())
            ranges = _sub_ranges("/etc/subgid", me)
            gids = {g for g in gids if any(s <= g < s + n for s, n in ranges) and g != ident.sub_gid}
        return sorted(gids)

    def shm_dir_for(self, name: str) -> Path:
        from ...channels import SHM_DIR  # (lazy: the cffi binding is not needed to start a guest)

        return SHM_DIR / name

    def prepare_dirs(self, run_dir: Path, shm_dir: Path) -> None:
        """The run folder and the run's shm folder: the appliance keeps ownership; the loop user
        writes through the group (set-gid folders, the loop's umask 007)."""
        ident = self.identity
        shm_dir.mkdir(mode=0o700, exist_ok=False)
        for d in (run_dir, shm_dir):
            if ident.mode == "root":
                os.chown(d, os.getuid(), ident.gid)
                os.chmod(d, 0o2770)
            elif ident.sub_uid is not None:
                os.chmod(d, 0o2770)  # the loop is a member of our group (mapped as its gid 0)
            else:
                os.chmod(d, 0o700)  # the loop is our uid

    async def prepare_limits(self, name: str, run_dir: Path, image: Path) -> RunLimits:
        """The run's cgroup (``name``: its folder's name) and its file system (``image`` mounted
        on ``run_dir``), before prepare_dirs; raises run_limits.NoRoom when the disk is full."""
        return await asyncio.to_thread(run_limits.prepare, self.settings, name, run_dir, image, self.identity.gid)

    def cgroup_name(self, run: int | str) -> str:
        return f"{run_limits.cgroups.PREFIX}{run_limits.tag(self.settings.data_dir)}-{run}"

    def config(
        self,
        exe: Path,
        run_dir: Path,
        shm_dir: Path,
        env: dict[str, str],
        read_only: list[Path],
        report_fd: int,
        limits: RunLimits | None = None,
    ) -> dict[str, Any]:
        ident = self.identity
        # The loop's priority, and the most any thread of the run may take (RLIMIT_RTPRIO): below
        # the safety watcher's (settings.watch_priority), so the run cannot starve it.
        prio = min(max(1, int(env.get("XRF_PRIO") or DEFAULT_PRIORITY)), max(1, self.settings.watch_priority - 1))
        lim = self.limits
        return {
            "mode": ident.mode,
            "uid": ident.uid,
            "gid": ident.gid,
            "sub_uid": ident.sub_uid,
            "sub_gid": ident.sub_gid,
            "device_gids": self.device_gids(),
            "devices": self.devices(),
            "exe": str(exe),
            "run_dir": str(run_dir),
            "shm_dir": str(shm_dir),
            "read_only": [str(p) for p in read_only],
            "env": env,
            "report_fd": report_fd,
            "priority": prio,
            "memory_mb": lim.memory_mb,
            "nproc": lim.nproc,
            "nofile": lim.nofile,
            "fsize_mb": lim.fsize_mb,
            "tmp_mb": lim.tmp_mb,
            "memlock_mb": lim.memlock_mb,
            "allow_missing": bool(self.settings.allow_unconfined),
            **(limits.launcher_config() if limits is not None else {}),
            # TEST ONLY: layers the launcher reports missing ("skipped for a test"), for the tests of
            # the dashboard's "runs WITHOUT" banner. Never set on a bench.
            **({"test_drop": dropped_for_a_test()} if dropped_for_a_test() else {}),
        }

    async def spawn(
        self,
        exe: Path,
        run_dir: Path,
        shm_dir: Path,
        env: dict[str, str],
        read_only: list[Path],
        output: Any,
        tag: str = "",
        timeout_s: float = 10.0,
        limits: RunLimits | None = None,
        shm_fd: int | None = None,
    ) -> tuple[children.Child, GuestReport]:
        """Start the launcher; return it and its report once the controller exec'd (or was refused:
        the process has then exited with guest.REFUSED_EXIT and ``report.error`` says why).
        `shm_fd`: the run's segment (channels.segment.create_sealed), passed to the launcher and
        the controller under its number (``env`` names it: XRF_SHM_FD)."""
        bad = sorted(set(env) - guest.ENV_ALLOWED)
        if bad:
            raise ValueError(f"environment not on the allow-list: {', '.join(bad)}")
        r, w = os.pipe()
        try:
            cfg = self.config(exe, run_dir, shm_dir, env, read_only, w, limits)
            if shm_fd is not None:
                cfg["shm_fd"] = shm_fd
            # The launcher's own environment: XRF_RUN_DIR identifies the run (the orphan reaper checks
            # /proc/<launcher>/environ before signalling a launcher left by an earlier appliance).
            launcher_env = {
                "PATH": "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
                "LANG": "C.UTF-8",
                "XRF_SHM": tag,
                "XRF_RUN_DIR": str(run_dir),
                # Where the launcher keeps the segment: a restarted appliance reopens it there
                # (/proc/<launcher>/fd/<n>, server/runs/orphans.py).
                **({"XRF_SHM_FD": str(shm_fd)} if shm_fd is not None else {}),
            }
            # children.spawn: fds 0-2, the report pipe and the segment only (uvloop's subprocess would pass on
            # every inheritable descriptor of ours to the launcher).
            proc = children.spawn(
                launcher_argv(cfg),
                pass_fds=(w,) if shm_fd is None else (w, shm_fd),
                cwd="/",
                env=launcher_env,
                stdin=subprocess.DEVNULL,
                stdout=output,
                stderr=subprocess.STDOUT,
                # Own session: a Ctrl-C on the appliance's terminal reaches the appliance only,
                # which then stops the run in order (quit, signals).
                start_new_session=True,
                # Not tied to us: the loop runs on if the appliance dies (host_timeout_action).
                tied=False,
            )
        finally:
            os.close(w)
        try:
            raw = await asyncio.wait_for(asyncio.to_thread(_read_all, r), timeout_s)
        finally:
            os.close(r)
        report = GuestReport()
        try:
            data = json.loads(raw.decode().splitlines()[0]) if raw.strip() else {}
        except (ValueError, IndexError):
            data = {}
        if data:
            report = GuestReport(
                mode=data.get("mode", "none"),
                layers=data.get("layers", {}),
                notes=data.get("notes", []),
                error=data.get("error", ""),
                pid=int(data.get("pid", 0)),
            )
        else:
            report.error = "the sandbox launcher ended without a report (see the run's output)"
        return proc, report


def launcher_argv(cfg: dict[str, Any]) -> list[str]:
    """The launcher's command line: our Python without site packages (it needs none)."""
    boot = (
        f"import sys; sys.path.insert(0, {str(APPLIANCE_DIR)!r}); from xrflab.guest import main; "
        "sys.exit(main(sys.argv[1:]))"
    )
    return [sys.executable, "-S", "-B", "-c", boot, json.dumps(cfg)]


def _read_all(fd: int) -> bytes:
    out = b""
    while chunk := os.read(fd, 65536):
        out += chunk
    return out


def probe(settings: Any) -> GuestReport:
    """Start /bin/true in the sandbox as a run would (for ``xrf doctor`` and the System page)."""
    import tempfile

    async def go() -> GuestReport:
        spawner = GuestSpawner(settings)
        with tempfile.TemporaryDirectory(prefix="xrf-probe-") as tmp:
            run_dir = Path(tmp) / "run"
            run_dir.mkdir()
            shm_dir = spawner.shm_dir_for(f"xrf-probe-{os.getpid()}")
            limits = None
            try:
                os.chmod(tmp, 0o755)
                limits = await spawner.prepare_limits(
                    spawner.cgroup_name(f"probe{os.getpid()}"), run_dir, Path(tmp) / "run.img"
                )
                spawner.prepare_dirs(run_dir, shm_dir)
                true = shutil.which("true") or "/bin/true"
                with open(os.devnull, "wb") as out:
                    proc, report = await spawner.spawn(
                        Path(true), run_dir, shm_dir, {"PATH": "/usr/bin:/bin"}, [], out, limits=limits
                    )
                await proc.wait()
                return report
            finally:
                if limits is not None:
                    await asyncio.to_thread(limits.release)
                shutil.rmtree(shm_dir, ignore_errors=True)

    return asyncio.run(go())
