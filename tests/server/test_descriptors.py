"""Issue 14 item 3: no child of the appliance inherits a descriptor it should not have.

A real appliance is started with an inheritable "canary" file descriptor (as a careless parent
would leak one). While it runs a controller (the loop, its live rerun proxy, the ROS 2 bridge),
a self-check and a project build, every descendant's /proc/<pid>/fd is sampled every few ms. No
descriptor above 2 of any descendant may be the listening socket, the canary, or any socket, pipe
or file the appliance itself holds open. Then, with a run active, the appliance is killed with
SIGKILL: a new appliance must bind the same port at once (no orphan keeps the socket).
"""

from __future__ import annotations

import ctypes
import errno
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from xrf_testing.grpcweb import watch_live
from xrf_testing.harness import (
    ADMIN_PASSWORD,
    ADMIN_USER,
    HERE,
    REPO_ROOT,
    Server,
    free_port,
    login_client,
    shared_builds_root,
    wait_for,
)
from xrf_testing.hostile import project_files
from xrf_testing.projects_support import reachable_tmp, targz
from xrf_testing.ros import isolated_ros_env, require_rclpy

# Shared with the appliance and its children legitimately (each opens its own): not inherited.
OWN_OPENS = (
    "/dev/null",
    "/dev/urandom",
    "/dev/random",
    "/dev/shm/",
    "/proc/",
    "/sys/",
    "/dev/cpu_dma_latency",
    "/dev/pts/",
    "/dev/tty",
)


def _start(
    data_dir: Path, port: int, pass_fds: tuple[int, ...] = (), builds_root: Path | None = None, **settings: object
) -> Server:
    """tests/xrf_testing/harness.start_server, on a given port and with descriptors passed on."""
    config = {
        "data_dir": str(data_dir),
        "builds_root": str(builds_root or shared_builds_root()),
        "port": port,
        "host": "127.0.0.1",
        "real_bench": False,
        **settings,
    }
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join([str(REPO_ROOT / "appliance"), str(HERE)]),
        XRF_BOOTSTRAP_ADMIN_PASSWORD=ADMIN_PASSWORD,
    )
    proc = subprocess.Popen(
        [sys.executable, str(HERE / "serve_for_test.py"), json.dumps(config)],
        env=env,
        pass_fds=pass_fds,
        stdin=subprocess.DEVNULL,
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while True:
        try:
            if httpx.get(url + "/api/health", timeout=2).status_code == 200:
                break
        except httpx.TransportError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            raise RuntimeError(f"appliance did not start on port {port} (exit {proc.poll()})")
        time.sleep(0.05)
    return Server(url, f"ws://127.0.0.1:{port}/ws", proc, data_dir, login_client(url, ADMIN_USER, ADMIN_PASSWORD))


def _children_map() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            stat = Path(f"/proc/{name}/stat").read_text()
        except OSError:
            continue
        ppid = int(stat[stat.rindex(")") + 2 :].split()[1])
        kids.setdefault(ppid, []).append(int(name))
    return kids


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True


def descendants(root: int) -> list[int]:
    kids = _children_map()
    out, todo = [], [root]
    while todo:
        for k in kids.get(todo.pop(), []):
            out.append(k)
            todo.append(k)
    return out


_SYS_KCMP = {"x86_64": 312, "aarch64": 272, "armv7l": 378}.get(platform.machine())
_KCMP_FILE = 0
_libc = ctypes.CDLL(None, use_errno=True)


def same_open_file(pid1: int, fd1: int, pid2: int, fd2: int) -> bool | None:
    """True: the two descriptors are one open file description (one was inherited or passed
    from the other); False: two separate opens, or one of them is gone (EBADF/ESRCH: nothing is
    shared any more); None: cannot tell (kcmp refused or unknown here)."""
    if _SYS_KCMP is None:
        return None
    r = _libc.syscall(_SYS_KCMP, pid1, pid2, _KCMP_FILE, fd1, fd2)
    if r >= 0:
        return r == 0  # 0: the same; 1, 2, 3: different
    return False if ctypes.get_errno() in (errno.EBADF, errno.ESRCH) else None


def fd_targets(pid: int) -> dict[int, str]:
    out = {}
    try:
        names = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return out
    for n in names:
        try:
            out[int(n)] = os.readlink(f"/proc/{pid}/fd/{n}")
        except OSError:
            continue
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode("utf-8", "replace").strip()
    except OSError:
        return ""


def listening_inode(port: int) -> str:
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if int(f[1].rsplit(":", 1)[1], 16) == port and f[3] == "0A":
                return f"socket:[{f[9]}]"
    raise AssertionError(f"nothing listens on port {port}")


@dataclass
class Sampler:
    """Every few ms: each descendant of `root` and its descriptors above 2."""

    root: int
    forbidden: set[str]
    # pid -> every command line it had: a child sampled between fork and exec still shows the
    # appliance's own command line, so the first one alone may never name what it became
    seen: dict[int, set[str]] = field(default_factory=dict)
    fds: dict[int, dict[int, str]] = field(default_factory=dict)  # pid -> fd -> target (first seen)
    bad: list[str] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)

    def _main(self) -> None:
        while not self._stop.is_set():
            ours: dict[str, list[int]] = {}  # the appliance's open targets -> its fd numbers
            for rfd, t in fd_targets(self.root).items():
                if t.startswith(("socket:", "pipe:", "/")) and not t.startswith(OWN_OPENS):
                    ours.setdefault(t, []).append(rfd)
            own = cmdline(self.root)
            for pid in descendants(self.root):
                cmd = cmdline(pid)
                if not cmd:
                    continue
                self.seen.setdefault(pid, set()).add(cmd)
                if cmd == own:
                    # forked, not yet exec'd: it holds the appliance's descriptors until the close
                    # before exec (subprocess closes them after preexec_fn); what it inherits is
                    # judged once it is the program it runs
                    continue
                for fd, target in fd_targets(pid).items():
                    if fd <= 2:
                        continue
                    self.fds.setdefault(pid, {}).setdefault(fd, target)
                    # The run sandbox's launcher is passed one pipe on purpose: its report to the
                    # appliance (pass_fds); the controller it execs gets none of it. The run's
                    # segment (a sealed memfd the appliance made) goes to the launcher and on to
                    # the controller on purpose too, and to nothing else.
                    passed = ("xrflab.guest" in cmd and target.startswith("pipe:")) or (
                        target.startswith("/memfd:xrf-run-") and self._in_sandbox(pid)
                    )
                    if target in self.forbidden or (
                        target in ours and not passed and self._shares(pid, fd, ours[target])
                    ):
                        self.bad.append(f"pid {pid} ({cmd[:120]}): fd {fd} -> {target}")
            time.sleep(0.005)

    def _in_sandbox(self, pid: int) -> bool:
        """`pid` is the run sandbox's launcher or runs below it (its init, the controller)."""
        while pid > 1 and pid != self.root:
            if "xrflab.guest" in cmdline(pid):
                return True
            try:
                pid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                return False
        return False

    def _shares(self, pid: int, fd: int, root_fds: list[int]) -> bool:
        """Is `pid`'s fd one of the appliance's open file descriptions (inherited or passed), not
        its own open of the same path? A path says only which file: the run sandbox's launcher
        opens the run folder itself (O_PATH, for its bind mounts) while the appliance's log writer
        has it open too. kcmp(KCMP_FILE) compares the open files themselves; where the kernel
        refuses it (no permission, unknown architecture), the same target counts as shared."""
        for rfd in root_fds:
            same = same_open_file(self.root, rfd, pid, fd)
            if same is None:
                return True
            if same:
                return True
        return False

    def matching(self, text: str) -> list[int]:
        return [p for p, cmds in self.seen.items() if any(text in c for c in cmds)]


def _canary(tmp_path: Path) -> tuple[int, str]:
    path = tmp_path / "canary-inherited-by-the-appliance"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    os.set_inheritable(fd, True)
    return fd, os.readlink(f"/proc/self/fd/{fd}")


def _reap(pids: list[int]) -> None:
    """End processes this test started (through the appliance) that outlived it."""
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


@pytest.fixture
def ros_env() -> Iterator[dict[str, str]]:
    require_rclpy()
    env = isolated_ros_env(201, 230)
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    yield env
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def test_children_inherit_nothing(tmp_path: Path, ros_env: dict[str, str]) -> None:
    data = reachable_tmp("fds")
    canary_fd, canary = _canary(tmp_path)
    port = free_port()
    # Its own builds folder: the bundled example is configured and compiled from scratch by the
    # appliance (cmake, make, the compilers as its children) when the run starts.
    server = _start(data, port, pass_fds=(canary_fd,), builds_root=data / "example-builds")
    os.close(canary_fd)
    sampler = Sampler(server.proc.pid, {canary})
    started: list[int] = []
    try:
        listen = listening_inode(port)
        assert listen in fd_targets(server.proc.pid).values()
        # The appliance got the canary as an open descriptor: the test is able to fail.
        assert canary in fd_targets(server.proc.pid).values()
        sampler.forbidden.add(listen)
        sampler.start()
        http = server.http

        # A run: the loop, its live rerun proxy, the ROS 2 bridge.
        assert http.post("/api/ros", json={"enabled": True}).status_code == 200
        with server.ws() as ws:
            server.stop_run()
            run = server.start_run("relbot")
            ws.wait_state("IDLE", timeout=30)
            for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
                assert ws.command(cmd)["accepted"], cmd
                ws.wait_state(state, timeout=10)
            assert watch_live(http).status == 200  # the proxy starts at the run's first viewer
            wait_for(
                lambda: sampler.matching("ros-bridge") and sampler.matching("serve-grpc"),
                60,
                "the ROS 2 bridge and the run's rerun proxy",
            )
            time.sleep(1.0)  # the point: the sampler watches both helpers at work a while
            server.stop_run()
            assert http.post("/api/ros", json={"enabled": False}).status_code == 200

            # A self-check (its helper process).
            r = http.post("/api/selfcheck", json={"profile": "relbot"})
            assert r.status_code == 202, r.text
            check = r.json()["id"]
            ws.wait_for(
                lambda m: (
                    m.get("type") == "selfcheck" and m.get("check") == check and m.get("event") in ("report", "error")
                ),
                timeout=120,
            )

        # A build of an uploaded project: the build sandbox (its success is the builder's business).
        files = {
            "file": (
                "mine.tar.gz",
                targz(project_files(REPO_ROOT / "student_projects/templates/base"), "mine"),
                "application/gzip",
            )
        }
        pid = http.post("/api/projects", files=files).json()["project"]["id"]
        b = http.post(f"/api/projects/{pid}/builds").json()
        b = wait_for(
            lambda: (
                (x := http.get(f"/api/projects/{pid}/builds/{b['id']}").json())["status"] not in ("queued", "building")
                and x
            ),
            600,
            "the build",
        )
        assert b["status"] in ("ok", "failed"), b
    finally:
        sampler.stop()
        started = [p for p in sampler.seen if p != server.proc.pid]
        server.http.close()
        server.proc.terminate()
        try:
            server.proc.wait(15)
        except subprocess.TimeoutExpired:
            server.proc.kill()
            server.proc.wait()
        _reap(started)
        shutil.rmtree(data, ignore_errors=True)

    assert sampler.matching(run["build"]) or sampler.matching("relbot"), sampler.seen
    for what in ("ros-bridge", "serve-grpc", "cmake", "xrflab.projects.builder --sandbox", "selfcheck"):
        assert sampler.matching(what), f"no {what} process seen: {sorted(set().union(*sampler.seen.values()))[:40]}"
    assert not sampler.bad, "\n".join(sorted(set(sampler.bad))[:40])


def test_port_free_again_after_kill_9_with_a_run_active(tmp_path: Path) -> None:
    data = reachable_tmp("fds-kill")
    port = free_port()
    first = _start(data, port)
    left: list[int] = []
    try:
        with first.ws() as ws:
            first.start_run("relbot")
            ws.wait_state("IDLE", timeout=30)
            assert ws.command("initialise")["accepted"]
            ws.wait_state("INITIALISED", timeout=10)

        def proxies() -> list[int]:
            return [p for p in descendants(first.proc.pid) if "--serve-grpc" in cmdline(p)]

        # The run's live rerun proxy starts at its first viewer.
        assert watch_live(first.http).status == 200
        rerun = wait_for(proxies, 30, "the run's live rerun proxy")
        left = descendants(first.proc.pid)
        assert left, "the run's processes"
        os.kill(first.proc.pid, signal.SIGKILL)
        first.proc.wait(10)
        first.http.close()
        # The run's live rerun proxy dies with the appliance (no server left with parent 1); the
        # loop itself lives on until the next appliance stops it.
        wait_for(
            lambda: not [p for p in rerun if Path(f"/proc/{p}").exists() and not _zombie(p)],
            5,
            "the rerun proxy to end with the appliance",
        )
        alive = [p for p in left if Path(f"/proc/{p}").exists()]
        second = _start(data, port)  # binds the same port, although the orphans may still live
        try:
            assert second.http.get("/api/health").status_code == 200
            for p in alive:
                assert listening_inode(port) not in fd_targets(p).values(), f"orphan {p} holds the socket"
        finally:
            second.http.close()
            second.proc.terminate()
            second.proc.wait(15)
    finally:
        if first.proc.poll() is None:
            first.proc.kill()
            first.proc.wait()
        _reap([p for p in left if Path(f"/proc/{p}").exists()])
        shutil.rmtree(data, ignore_errors=True)
