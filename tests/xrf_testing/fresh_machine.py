"""A fresh machine for the fresh-machine check (test_fresh_machine.py): a Debian 12 tree with
nothing of the project, entered the way a new user's VM would be used.

The tree is ``debootstrap --variant=minbase`` plus git and ca-certificates only (what a user who
ran ``git clone`` has): no python3, no compiler, no cmake, no chromium, no venv. It is cached
beside the installer's tree (deploy_support.ensure_debian_tree) and copied per module.

Into the copy go this machine's package-registry configuration, nothing else of the host:
apt's sources and Acquire settings, pip's configuration files and the local indexes/wheel
folders they name (bind-mounted read-only; the tester's own ~/.config/pip/pip.conf through
PIP_CONFIG_FILE, as the tree's HOME is fresh), resolv.conf and the CA bundle. The host's apt
archive is the lower layer of an overlay on the tree's: apt still resolves, fetches what is
missing and installs every package, and the host's folder is never written. pip gets no cache
of its own: here its distributions come from local file indexes or are not cacheable, and
unpacking them, not fetching, is its time.

`enter` runs a command in the tree as root with a fresh HOME, in its own mount and PID
namespaces: pivot_root (not chroot, so the kernel treats it as a machine's root: user namespaces
work as on a real one), /proc, /sys, /dev, a private /dev/shm; when the command ends, or the
test kills it, the PID namespace takes every process with it and the mount namespace every
mount. Nothing is left on the host.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from xrf_testing.deploy_support import REPO, ensure_debian_tree, source_snapshot

PACKAGES = ["git", "ca-certificates"]
HOME = "/root-fresh"
APT_ARCHIVES = "/var/cache/apt/archives"
USER_PIP_CONF = "/etc/xrf-fresh-user-pip.conf"  # the tester's own pip.conf, read through PIP_CONFIG_FILE
PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"

# Runs on the host's bash as PID 1 of the new namespaces; its arguments: N, N environment
# assignments for the command (values may hold spaces), then the command for the tree.
ENTER = r"""
set -euo pipefail
n="$1"
shift
pass=("${@:1:$n}")
shift "$n"
T="$XRF_TREE"
mount --bind "$T" "$T"
mount -t proc proc "$T/proc"
mount -t sysfs sysfs "$T/sys"
mount --rbind /dev "$T/dev"
mount -t tmpfs -o nosuid,nodev,mode=1777 tmpfs "$T/dev/shm"
IFS=: read -r -a ro <<<"$XRF_RO_BINDS"
for p in "${ro[@]}"; do
    [ -n "$p" ] || continue
    mkdir -p "$T$p"
    mount --bind "$p" "$T$p"
    mount -o remount,bind,ro "$T$p"
done
mount -t overlay overlay -o "lowerdir=$XRF_APT_ARCHIVES,upperdir=$XRF_APT_UPPER,workdir=$XRF_APT_WORK" \
    "$T$XRF_APT_ARCHIVES"
cd "$T"
mkdir -p .old-root
pivot_root . .old-root
cd /
umount -l /.old-root
rmdir /.old-root
rc=0
env -i HOME="$XRF_HOME" USER=root LOGNAME=root PATH="$XRF_PATH" LANG=C.UTF-8 "${pass[@]}" \
    bash -c 'cd "$0" && exec "$@"' "$XRF_CWD" "$@" || rc=$?
exit "$rc"
"""


def host_pip_env() -> list[str]:
    """This machine's PIP_* settings (indexes, find-links, certificate, timeout) whose paths the
    tree will also have."""
    env = [f"{k}={v}" for k, v in sorted(os.environ.items()) if k.startswith("PIP_") and k != "PIP_CONFIG_FILE"]
    if _user_pip_conf():
        env.append(f"PIP_CONFIG_FILE={USER_PIP_CONF}")
    return env


def _user_pip_conf() -> Path | None:
    """The pip configuration of the user running the tests (their HOME is not the tree's)."""
    for p in (
        os.environ.get("PIP_CONFIG_FILE", ""),
        Path.home() / ".config/pip/pip.conf",
        Path.home() / ".pip/pip.conf",
    ):
        if p and Path(p).is_file():
            return Path(p)
    return None


def _pip_paths() -> list[str]:
    """Local folders pip's configuration names here (find-links, file:// indexes)."""
    text = " ".join(v for k, v in os.environ.items() if k.startswith("PIP_"))
    for conf in (Path("/etc/pip.conf"), Path("/etc/xdg/pip/pip.conf"), _user_pip_conf()):
        if conf and conf.exists():
            text += " " + conf.read_text(errors="replace")
    paths = set()
    for word in text.replace("=", " ").split():
        p = word.removeprefix("file://")
        if p.startswith("/opt/") or p.startswith("/srv/"):
            top = Path(*Path(p).parts[:3])  # /opt/<name>: the whole local index, not one page
            if top.is_dir():
                paths.add(str(top))
    return sorted(paths)


@dataclass
class Machine:
    tree: Path
    checkout: str  # the checkout's path inside the tree (under /tmp)
    work: Path  # the overlay's upper/work folders, beside the tree

    def enter(self, command: list[str], timeout: float, cwd: str | None = None) -> subprocess.CompletedProcess:
        passed = host_pip_env()
        env = {
            "PATH": os.environ.get("PATH", PATH),
            "XRF_TREE": str(self.tree),
            "XRF_HOME": HOME,
            "XRF_PATH": PATH,
            "XRF_CWD": cwd or self.checkout,
            "XRF_RO_BINDS": ":".join(_pip_paths()),
            "XRF_APT_ARCHIVES": APT_ARCHIVES,
            "XRF_APT_UPPER": str(self.work / "apt-upper"),
            "XRF_APT_WORK": str(self.work / "apt-work"),
        }
        return subprocess.run(
            [
                "unshare",
                "--mount",
                "--pid",
                "--fork",
                "--kill-child=SIGKILL",
                "--propagation",
                "private",
                "bash",
                "-c",
                ENTER,
                "enter",
                str(len(passed)),
                *passed,
                *command,
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )


def _copy_registry_config(tree: Path) -> None:
    etc = tree / "etc"
    # apt: the host's sources (same suites and mirror as its archive cache) and Acquire settings
    (etc / "apt/sources.list").unlink(missing_ok=True)
    for p in [Path("/etc/apt/sources.list"), *Path("/etc/apt/sources.list.d").glob("*")]:
        if p.is_file() and p.suffix in (".list", ".sources"):
            dest = etc / "apt" / p.relative_to("/etc/apt")
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(p, dest)
    for p in Path("/etc/apt/apt.conf.d").glob("*"):
        if p.is_file() and "Acquire::" in p.read_text(errors="replace"):
            shutil.copyfile(p, etc / "apt/apt.conf.d" / p.name)
    # pip: the global configuration files (their local folders are bound read-only by enter())
    for p in (Path("/etc/pip.conf"), Path("/etc/xdg/pip")):
        if p.is_file():
            shutil.copyfile(p, etc / p.name)
        elif p.is_dir():
            shutil.copytree(p, etc / p.relative_to("/etc"), dirs_exist_ok=True)
    user_conf = _user_pip_conf()
    if user_conf:
        shutil.copyfile(user_conf, tree / USER_PIP_CONF.lstrip("/"))
    for f in ("resolv.conf", "ssl/certs/ca-certificates.crt"):
        target = etc / f
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.is_symlink() or target.exists():
            target.unlink()
        shutil.copyfile(Path("/etc") / f, target)
    # What container images do: dpkg does not fsync every file it unpacks (the tree is thrown away;
    # the same packages are installed, the unpacking of ~400 of them just waits less on the disk).
    (etc / "dpkg/dpkg.cfg.d/xrf-fresh-unsafe-io").write_text("force-unsafe-io\n")
    # A chroot's usual guard: package scripts do not start daemons (mosquitto, ...) in the tree.
    policy = tree / "usr/sbin/policy-rc.d"
    policy.write_text("#!/bin/sh\nexit 101\n")
    policy.chmod(0o755)


def clone_or_snapshot(dest: Path) -> None:
    """What a new user has: a `git clone` of this checkout's HEAD (the committed state: others'
    half-done edits in a shared checkout are not the project). Outside a git checkout, a copy of
    the files made a one-commit repository (the suite's leak check reads `git status`)."""
    dest.parent.mkdir(parents=True)
    if (REPO / ".git").exists():
        subprocess.run(
            ["git", "-c", f"safe.directory={REPO / '.git'}", "clone", "-q", "--no-hardlinks", str(REPO), str(dest)],
            check=True,
        )
        return
    source_snapshot(dest)
    git = ["git", "-C", str(dest), "-c", "user.name=fresh-machine", "-c", "user.email=fresh@localhost"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "--", "."], check=True)
    subprocess.run([*git, "commit", "-q", "-m", f"snapshot of {REPO}"], check=True)


def make_machine(dest: Path) -> Machine:
    """A copy of the cached fresh tree at dest/root with a checkout of the project under /tmp."""
    src = ensure_debian_tree(PACKAGES)
    tree = dest / "root"
    subprocess.run(["cp", "-a", str(src), str(tree)], check=True)
    _copy_registry_config(tree)
    (tree / HOME.lstrip("/")).mkdir(mode=0o700)
    work = dest / "work"
    for d in ("apt-upper", "apt-work"):
        (work / d).mkdir(parents=True)
    checkout = f"/tmp/fresh-{os.getpid()}-{int(time.time())}/xrf-lab"
    clone_or_snapshot(tree / checkout.lstrip("/"))
    return Machine(tree, checkout, work)
