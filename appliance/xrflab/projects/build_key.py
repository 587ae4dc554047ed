"""What a build is reused by: its source tree's hash and the toolchain's identity.

A build of the same source (``source_hash``: every file's path and content) with the same
toolchain (``toolchain_id``: cmake's and the compiler's versions and a hash of rt_core and the
message generator) gives the same executable, so it is not built again (``Builder.submit``).
A version of a project is found from its builds by the same hash (``versions.py``).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path


def _first_line(cmd: list[str]) -> str:
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=10)
        return (r.stdout or r.stderr).splitlines()[0].strip()
    except (OSError, IndexError, subprocess.SubprocessError):
        return f"{cmd[0]}: not found"


_TOOLCHAIN: str | None = None


def toolchain() -> str:
    """cmake's and the C++ compiler's versions (asked once per appliance)."""
    global _TOOLCHAIN
    if _TOOLCHAIN is None:
        cxx = os.environ.get("CXX") or "c++"
        _TOOLCHAIN = "; ".join([_first_line(["cmake", "--version"]), _first_line([cxx, "--version"])])
    return _TOOLCHAIN


def toolchain_id() -> str:
    from .. import build

    digest = build._content_hash(
        [
            build.REPO_ROOT / "rt_core",
            build.REPO_ROOT / "appliance/xrflab/msgdef.py",
            build.REPO_ROOT / "appliance/xrflab/twentysim_params.py",
        ]
    )
    return f"{toolchain()}; rt_core {digest}"


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
