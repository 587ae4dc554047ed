"""The run sandbox's launcher (xrflab.guest) for each kind of appliance user: root (a dedicated
user), an ordinary user with subordinate ids (user namespace + newuidmap), and an ordinary user
without them (refused unless an educator allowed it). What the controller sees is read by a
shell probe running in the sandbox."""

from __future__ import annotations

import contextlib
import json
import os
import pwd
import re
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
TEST_USER = "xrf-test-guest"  # an ordinary user with subordinate ids (made here when root)
# What the kernel offers no non-root appliance on this machine: cgroup v1 (a v1 cgroup takes a
# process of another uid only from root; the Pi's cgroup v2 with systemd's Delegate= would);
# the run folder's own file system comes from the root helper (server/runs/disk_helper.py) when it runs.
NON_ROOT_MISSING = {"memory", "pids", "cpu"}
# Fills the run folder beyond its 16 MB file system (guest_probe.py's limit) and says whether it stayed bounded.
FILL = r"""
dd if=/dev/zero of="$PWD/fill" bs=1M count=32 2>/dev/null
[ "$(du -m "$PWD/fill" | cut -f1)" -le 16 ] && echo "disk=bounded" || echo "disk=UNBOUNDED"
"""
PROBE = r"""#!/bin/sh
echo "uid=$(id -u)"
echo "caps=$(grep CapEff /proc/self/status | cut -f2)"
echo "nnp=$(grep NoNewPrivs /proc/self/status | cut -f2)"
echo "pid=$$"
echo "ppid=$(cut -d' ' -f4 /proc/$$/stat)"
echo "root=$(ls / | tr '\n' ' ')"
echo "fds=$(ls /proc/self/fd | tr '\n' ' ')"
echo "env=$(env | cut -d= -f1 | sort | tr '\n' ' ')"
echo "lo=$(cat /sys/class/net/lo/operstate 2>/dev/null || echo none)"
touch /tmp/x && echo "tmp=writable"
touch "$PWD/written" && echo "run=writable"
touch /etc/x 2>/dev/null && echo "etc=WRITABLE" || echo "etc=read-only"
"""


def probe_as(
    user: str | None,
    tmp: Path,
    allow_missing: bool = False,
    no_newuidmap: bool = False,
    script: str = PROBE,
    helper: tuple[Path, str] | None = None,
) -> dict[str, Any]:
    # pytest's tmp_path is private to its user: the probe lives where another user may read it.
    tmp = Path(tempfile.mkdtemp(prefix="xrf-probe-"))
    os.chmod(tmp, 0o755)
    try:
        return _probe_as(user, tmp, allow_missing, no_newuidmap, script, helper)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _probe_as(
    user: str | None, tmp: Path, allow_missing: bool, no_newuidmap: bool, text: str, helper: tuple[Path, str] | None
) -> dict[str, Any]:
    script = tmp / "probe.sh"
    script.write_text(text)
    script.chmod(0o755)
    os.chmod(tmp, 0o755)
    python = sys.executable
    cmd = [python, str(HERE / "guest_probe.py"), str(REPO / "appliance"), str(script), "1" if allow_missing else "0"]
    if helper is not None:
        cmd += [str(helper[0]), helper[1]]
    if user is not None:
        # Another user cannot reach a venv under /root: the system's Python runs the same code.
        python = shutil.which("python3", path="/usr/bin:/bin") or "/usr/bin/python3"
        cmd = [
            shutil.which("setpriv") or "/usr/bin/setpriv",
            f"--reuid={user}",
            f"--regid={pwd.getpwnam(user).pw_gid}",
            "--init-groups",
            python,
            *cmd[1:],
        ]
    # Without newuidmap on PATH the appliance has no way to a second uid, as without /etc/subuid.
    env = dict(os.environ, PATH="/nonexistent") if no_newuidmap else None
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd="/", env=env)
    assert r.returncode == 0 and r.stdout.strip(), r.stderr
    data = json.loads(r.stdout.strip().splitlines()[-1])
    data["seen"] = dict(re.findall(r"^(\w+)=(.*)$", data["output"], re.M))
    return data


def assert_confined(data: dict[str, Any], except_layers: set[str] = frozenset()) -> None:  # type: ignore[assignment]
    report, seen = data["report"], data["seen"]
    assert set(report["missing"]) == set(except_layers), report
    assert data["rc"] == 0, data["output"]
    # No capability, except where root itself may not raise RLIMIT_RTPRIO/MEMLOCK (no
    # CAP_SYS_RESOURCE, as in some containers): then exactly CAP_SYS_NICE and CAP_IPC_LOCK, said in a note.
    kept = (1 << 23) | (1 << 14) if any("kept CAP_" in n for n in report["notes"]) else 0
    assert seen["uid"] != "0" and int(seen["caps"], 16) & ~kept == 0 and seen["nnp"] == "1", seen
    # In its own PID namespace, the only child of the sandbox's init (guest._init).
    assert seen["pid"] == "2" and seen["ppid"] == "1", seen
    assert set(seen["root"].split()) <= {
        "bin",
        "dev",
        "etc",
        "lib",
        "lib32",
        "lib64",
        "libx32",
        "proc",
        "sbin",
        "sys",
        "tmp",
        "usr",
        "var",
        "xrf",
    }, seen
    assert seen["fds"].split() == ["0", "1", "2", "3"], seen  # 3: ls's own listing of the folder
    assert set(seen["env"].split()) <= {"PATH", "PWD", "OLDPWD", "SHLVL", "_"}, seen
    assert seen["lo"] in ("down", "none"), seen
    assert seen["tmp"] == "writable" and seen["run"] == "writable" and seen["etc"] == "read-only", seen


def ensure_test_user() -> str:
    """As root: an ordinary user with a range in /etc/subuid and /etc/subgid (uidmap installed by ./lab)."""
    try:
        pwd.getpwnam(TEST_USER)
    except KeyError:
        subprocess.run(
            [
                "useradd",
                "--system",
                "--user-group",
                "--no-create-home",
                "--home-dir",
                "/nonexistent",
                "--shell",
                "/usr/sbin/nologin",
                TEST_USER,
            ],
            check=True,
        )
    for f, flag in (("/etc/subuid", "--add-subuids"), ("/etc/subgid", "--add-subgids")):
        text = Path(f).read_text() if Path(f).exists() else ""
        if not re.search(rf"^{TEST_USER}:", text, re.M):
            subprocess.run(["usermod", flag, "720000-785535", TEST_USER], check=True)
    return TEST_USER


def test_a_controller_dies_of_a_signal_it_raises_itself(tmp_path: Path) -> None:
    """As a namespace's PID 1 it would not (the kernel drops such signals for an init): a
    student's raise(SIGSEGV) or abort() must end the run as it would on XRF2, and the launcher
    mirrors that signal."""
    data = probe_as(None, tmp_path, allow_missing=True, script="#!/bin/sh\nkill -ABRT $$\necho survived\n")
    assert data["rc"] == -6 and "survived" not in data["output"], data


def test_as_this_user(tmp_path: Path) -> None:
    """Root: the dedicated user. Not root: the user namespace, with subordinate ids if we have them."""
    data = probe_as(None, tmp_path)
    if os.geteuid() == 0:
        assert data["report"]["mode"] == "root"
        assert_confined(data)
        assert int(data["seen"]["uid"]) == pwd.getpwnam("xrf-run").pw_uid
    elif data["report"]["missing"]:
        assert data["rc"] == 126 and "subordinate" in data["error"] and "--allow-unconfined" in data["error"]
    else:
        assert_confined(data)


@contextlib.contextmanager
def run_disk_helper(owner: str) -> Iterator[tuple[Path, str]]:
    """As root: a data folder of `owner`'s and the root helper that makes its run folders file
    systems of their own (deploy/systemd/xrf-run-disk.service on a Pi), on a socket of its own."""
    base = Path(tempfile.mkdtemp(prefix="xrf-helper-"))
    os.chmod(base, 0o755)
    data, images, sock = base / "data", base / "images", base / "run-disk.sock"
    (data / "runs").mkdir(parents=True)
    for d in (data, data / "runs"):
        shutil.chown(d, owner, pwd.getpwnam(owner).pw_gid)
    helper = subprocess.Popen(
        [sys.executable, "-m", "xrflab.server.runs.disk_helper", "--data", str(data), "--images", str(images)]
        + ["--owner", owner, "--socket", str(sock), "--max-mb", "16", "--max-files", "256"],
        env=dict(os.environ, PYTHONPATH=str(REPO / "appliance")),
    )
    try:
        deadline = time.monotonic() + 20
        while not sock.exists():
            assert helper.poll() is None and time.monotonic() < deadline, "the run-disk helper did not start"
            time.sleep(0.05)
        yield data, str(sock)
    finally:
        helper.terminate()
        helper.wait(timeout=10)
        shutil.rmtree(base, ignore_errors=True)


def test_ordinary_user_with_subordinate_ids(tmp_path: Path) -> None:
    """The Pi's case: an appliance that is not root, with subordinate ids; the run folder made a
    file system of its own by the root helper (as root here; without it, `disk` is missing too)."""
    if os.geteuid() != 0:
        data = probe_as(None, tmp_path, allow_missing=True)
        if "user" in data["report"]["missing"]:  # this user has no /etc/subuid range: refused, clearly
            refused = probe_as(None, tmp_path)
            assert refused["rc"] == 126 and "subordinate" in refused["error"]
            return
        assert_confined(data, except_layers=NON_ROOT_MISSING | {"disk"})
    else:
        user = ensure_test_user()
        with run_disk_helper(user) as helper:
            data = probe_as(user, tmp_path, allow_missing=True, helper=helper, script=PROBE + FILL)
            assert_confined(data, except_layers=NON_ROOT_MISSING)
            assert data["seen"]["disk"] == "bounded", data["output"]
            # Released: an ordinary folder again, with what the controller wrote in it.
            run_dir = Path(data["run_dir"])
            assert (run_dir / "written").is_file() and os.stat(run_dir).st_dev == os.stat(run_dir.parent).st_dev
            assert not list((helper[0].parent / "images").glob("*.img"))
    assert data["report"]["mode"] == "userns"
    # The files the controller wrote belong to its own host uid, neither root nor the appliance's.
    assert data["seen"]["uid"] == "1"


def test_no_subordinate_ids_refused_unless_allowed(tmp_path: Path) -> None:
    """No second uid to be had (no newuidmap; as root: `nobody`, which has no /etc/subuid range)."""
    user = "nobody" if os.geteuid() == 0 else None
    refused = probe_as(user, tmp_path, no_newuidmap=True)
    missing = {"user", "disk"} | NON_ROOT_MISSING  # no helper runs for this one
    assert refused["rc"] == 126 and set(refused["report"]["missing"]) == missing
    assert "REFUSED" in refused["output"] and "--allow-unconfined" in refused["error"]
    assert "written" not in refused["output"]
    allowed = probe_as(user, tmp_path, allow_missing=True, no_newuidmap=True)
    assert_confined(allowed, except_layers=missing)
    assert allowed["seen"]["uid"] == "65534"  # unmapped in its nested namespace: no identity, no capability


def test_launcher_left_nothing(tmp_path: Path) -> None:
    probe_as(None, tmp_path)
    left = [p for p in Path("/dev/shm").iterdir() if p.name.startswith("xrf-guest-test-")]
    assert not left, left
    assert stat.S_ISDIR(os.stat(tmp_path).st_mode)


# A launcher with a second thread, as every process under qemu-user has (the arm64 rehearsal).
THREADED_LAUNCHER = r"""
import threading
from xrflab import guest
stop = threading.Event()
threading.Thread(target=stop.wait, daemon=True).start()
launch = guest._Launch.__new__(guest._Launch)
launch.cfg = {}
try:
    launch._enter_userns(0)
    print("entered")
except guest.GuestError as exc:
    print(exc)
"""


def test_a_multithreaded_launcher_is_told_why_it_gets_no_user_namespace() -> None:
    out = subprocess.run([sys.executable, "-c", THREADED_LAUNCHER], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "this process has 2 threads" in out.stdout, out.stdout
    assert "single-threaded" in out.stdout and "qemu-user" in out.stdout, out.stdout
