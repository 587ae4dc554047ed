"""Who a build runs as, and what that user may reach.

As root the appliance builds as the dedicated unprivileged user ``xrf-build`` (created on first
use; the run sandbox's ``xrf-run`` is made the same way, server/runs/guest_spawn.py); without root a
build runs as the appliance's own user. The build user reads exactly what a build needs: the
folders down to its build folder may be passed (``o+x``, never listed), the project's source is
shared through the group (never through "other" bits: a data-folder file is never
world-readable), and it needs a Python it may run. Each function does nothing when the build runs
as the appliance's own uid.
"""

from __future__ import annotations

import os
import pwd
import stat
import subprocess
import sys
from pathlib import Path

# The description (passwd's comment field) of the two users the appliance creates: what `getent
# passwd` and user lists show an administrator, so each says what it is for.
BUILD_USER_COMMENT = "XRF Lab student builds"
RUN_USER_COMMENT = "XRF Lab student controllers (runs)"
_OUR_COMMENTS = (BUILD_USER_COMMENT, RUN_USER_COMMENT)


def ensure_build_user(name: str, comment: str = BUILD_USER_COMMENT) -> tuple[int, int, str]:
    """(uid, gid, note). As root: the dedicated user, created if missing (with `comment` as its
    description). Else: ourselves."""
    if os.geteuid() != 0:
        return os.getuid(), os.getgid(), f"not root: builds run as the appliance's own user (uid {os.getuid()})"
    try:
        pw = pwd.getpwnam(name)
        if pw.pw_gecos != comment and pw.pw_gecos in _OUR_COMMENTS:
            # Made by an earlier appliance with the other user's description (xrf-run was created
            # as "XRF Lab student builds"): corrected. An administrator's own text is left alone.
            subprocess.run(["usermod", "--comment", comment, name], capture_output=True, text=True)
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
                comment,
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


def check_reachable(path: Path, uid: int, gid: int, base: Path) -> None:
    """The build user must pass every folder down to ``path``. Our own folders inside ``base``
    (the data folder) get search permission for others (``o+x``: pass, never list or read; the
    0o077 umask left them without); anything else that blocks it is an error to fix by hand."""
    if uid == os.getuid():
        return
    base = base.resolve()
    for parent in [*reversed(path.parents)]:
        st = parent.stat()
        if st.st_mode & 0o001 or (st.st_uid == uid and st.st_mode & 0o100) or (st.st_gid == gid and st.st_mode & 0o010):
            continue
        if parent.resolve().is_relative_to(base) and st.st_uid == os.getuid():
            os.chmod(parent, stat.S_IMODE(st.st_mode) | 0o001)
            continue
        raise RuntimeError(
            f"the build user cannot reach {parent} (no search permission): put the appliance's "
            "data folder where other users may pass (chmod o+x)"
        )


def share_source(src: Path, uid: int, gid: int) -> None:
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


def python_for(uid: int) -> str:
    """A Python the build user may run: the appliance's own when it is reachable (its venv may
    sit in a private home), else the system's."""
    if uid == os.getuid():
        return sys.executable
    for cand in (sys.executable, "/usr/bin/python3", "/usr/local/bin/python3"):
        if _reachable_by_other(Path(cand)):
            return cand
    raise RuntimeError("no Python the build user may run (the appliance's is private): install python3")


def _reachable_by_other(path: Path) -> bool:
    try:
        real = path.resolve()
        for parent in real.parents:
            if not parent.stat().st_mode & 0o001:
                return False
        return bool(real.stat().st_mode & 0o001)
    except OSError:
        return False
