"""A download's conversion child run as the appliance runs it (logs/convert_child.py main, its
environment, the log handed over as a descriptor), reporting what it mapped and its peak RSS: for
the tests of what a child loads and how large it grows (tests/logs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from xrflab.logs.convert_child import _child_env

LIBS = ("libarrow", "libparquet", "numpy", "scipy", "rerun_bindings")  # what a light child must not map

# Its last two lines on stderr: the LIBS it mapped, and its VmHWM in kB (per process, unlike
# getrusage's, which a child inherits from its parent at exec).
_CODE = (
    "import sys; from xrflab.logs.convert_child import main; rc = main(sys.argv[1:]); sys.stdout.flush(); "
    "maps = open('/proc/self/maps').read(); "
    f"print(sorted({{m for m in {LIBS!r} if m in maps}}), file=sys.stderr); "
    "print([l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1], file=sys.stderr); "
    "sys.exit(rc)"
)


def convert_in_child(
    log: Path, fmt: str, target: str, changes: list[dict[str, Any]] | None = None
) -> tuple[bytes, str, int]:
    """(its stdout, the LIBS it mapped as text, its peak RSS in kB); fails on a non-zero exit."""
    fd = os.open(log, os.O_RDONLY)
    try:
        argv = [sys.executable, "-c", _CODE, str(fd), fmt, target, log.name]
        if changes and target == "-":
            argv += ["samples.csv", "changes.csv"]
        proc = subprocess.run(
            argv,
            input=json.dumps(changes or []).encode(),
            pass_fds=(fd,),
            capture_output=True,
            env=_child_env(),
            check=False,
        )
    finally:
        os.close(fd)
    err = proc.stderr.decode(errors="replace").strip().splitlines()
    assert proc.returncode == 0, err
    return proc.stdout, err[-2], int(err[-1])
