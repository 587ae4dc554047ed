"""rt_core's install where the build user can read it.

A build links rt_core from the appliance's cache (``build.ensure_rt_core``). That cache may be
private to the appliance's user (e.g. under /root), so a build that runs as another user gets a
world-readable copy in the projects folder (``.rt_core``), made once per rt_core install and put
in place by a rename: a build never sees half a copy.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path


def rt_core_for_user(projects_root: Path, prefix: Path, uid: int) -> Path | None:
    """An XRF_CACHE_DIR the build user can read holding rt_core's install ``prefix`` (None: the
    build runs as the appliance's user and uses the appliance's own cache)."""
    if uid == os.getuid():
        return None
    mirror = projects_root / ".rt_core"
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
