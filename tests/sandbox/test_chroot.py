"""The run sandbox where / is not a mount point (issue 30): an appliance in a chroot, as in an arm64
Debian root under qemu-user. The launcher said only "mount /: Invalid argument"; it must say exactly
why and what to do, and with what it says done (the chroot's folder bound onto itself) start and
confine as anywhere else.

The chroot is made here, in a mount namespace of its own (`unshare -m`, private: nothing reaches
this machine's mounts, and everything goes with the namespace): a plain folder with the host's
/usr, /etc, /dev, /proc, /sys, /tmp and the checkout bound in, entered with chroot(8), where
guest_probe.py runs a probe through the launcher as the appliance would. Root only (mount
namespaces, chroot)."""

from __future__ import annotations

import json
import os
import pwd
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import pytest
from test_launcher import PROBE, assert_confined

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
# The system's python3 runs the probe and the build sandbox, as in test_launcher.py for another user
# (the venv's interpreter may live outside the chroot).
PYTHON = shutil.which("python3", path="/usr/bin:/bin") or "/usr/bin/python3"

# $1: the chroot's folder; $2: "bind" to bind it onto itself first (what the refusal asks for);
# the rest: the command run in the chroot.
MAKE_CHROOT = r"""
set -eu
root="$1" how="$2"
shift 2
if [ "$how" = bind ]; then
    mount --bind "$root" "$root"
    mount --make-rprivate "$root"
fi
for d in usr etc dev proc sys tmp; do
    mkdir -p "$root/$d"
    mount --rbind "/$d" "$root/$d"
done
for l in bin lib lib32 lib64 sbin; do
    [ -L "/$l" ] && ln -s "$(readlink "/$l")" "$root/$l"
done
# the checkout (the system's python3 runs the probe, as in test_launcher.py for another user)
mkdir -p "$root$REPO"
mount --rbind "$REPO" "$root$REPO"
exec chroot "$root" "$@"
"""


def in_chroot(how: str, cmd: list[str], env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``cmd`` in a fresh chroot (its folder bound onto itself first when ``how`` is "bind")."""
    # the chroot's own folder: not a mount, and not below the /tmp bound into it
    root = Path(tempfile.mkdtemp(prefix="xrf-chroot-", dir="/var/tmp"))
    os.chmod(root, 0o755)  # it is /: every user passes through it (mkdtemp made it 0700)
    try:
        full = ["unshare", "--mount", "--propagation", "private", "sh", "-c", MAKE_CHROOT, "make-chroot"]
        return subprocess.run(
            [*full, str(root), how, *cmd],
            capture_output=True,
            text=True,
            timeout=120,
            cwd="/",
            env=dict(os.environ, REPO=str(REPO), **(env or {})),
        )
    finally:
        subprocess.run(["rm", "-rf", "--one-file-system", str(root)], check=False)


def probe_in_chroot(how: str) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="xrf-chroot-probe-"))
    try:
        os.chmod(tmp, 0o755)
        script = tmp / "probe.sh"
        script.write_text(PROBE)
        script.chmod(0o755)
        r = in_chroot(how, [PYTHON, str(HERE / "guest_probe.py"), str(REPO / "appliance"), str(script), "0"])
        assert r.returncode == 0 and r.stdout.strip(), r.stderr
        data = json.loads(r.stdout.strip().splitlines()[-1])
        data["seen"] = dict(re.findall(r"^(\w+)=(.*)$", data["output"], re.M))
        return data
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def build_in_chroot(how: str) -> subprocess.CompletedProcess[str]:
    """The build sandbox (python -m xrflab.projects.builder --sandbox, as the builder starts it)
    running `echo built` as nobody."""
    from xrflab.projects.sandbox_config import SandboxConfig, SandboxSpec

    nobody = pwd.getpwnam("nobody")
    spec = SandboxSpec(
        limits=SandboxConfig(rt_cpu=None), uid=nobody.pw_uid, gid=nobody.pw_gid, env={"PATH": "/usr/bin:/bin"}
    )
    cmd = [PYTHON, "-m", "xrflab.projects.builder", "--sandbox", spec.to_json(), "--", "/bin/echo", "built"]
    return in_chroot(how, cmd, env={"PYTHONPATH": str(REPO / "appliance")})


def need_root() -> None:
    if os.geteuid() != 0:
        pytest.skip(
            "as root only: making a chroot needs mount namespaces and chroot(2) (a non-root run proves nothing)"
        )


def test_refused_with_the_reason_and_the_fix_where_root_is_not_a_mount() -> None:
    need_root()
    data = probe_in_chroot("plain")
    assert data["rc"] == 126, data
    error = data["error"]
    assert "/ is not a mount point" in error and "mount --bind DIR DIR" in error, error
    assert "Invalid argument" not in error, error  # the bare errno it used to be


def test_starts_and_confines_once_the_root_is_bound_onto_itself() -> None:
    need_root()
    data = probe_in_chroot("bind")
    assert data["report"]["mode"] == "root", data
    assert_confined(data)


def test_build_sandbox_says_why_where_root_is_not_a_mount() -> None:
    """The build sandbox goes on without its private folders there (as it does wherever mounts are
    refused), and its log says exactly why instead of a bare errno."""
    need_root()
    r = build_in_chroot("plain")
    assert r.returncode == 0 and "built" in r.stdout, r.stdout + r.stderr
    assert "/ is not a mount point" in r.stdout and "mount --bind DIR DIR" in r.stdout, r.stdout


def test_build_sandbox_private_once_the_root_is_bound_onto_itself() -> None:
    need_root()
    r = build_in_chroot("bind")
    assert r.returncode == 0 and "built" in r.stdout, r.stdout + r.stderr
    assert "WARNING: no private" not in r.stdout and "sandbox: private /tmp" in r.stdout, r.stdout
