"""A run's log files, found and opened through its run folder: for the log routes
(server/http/logs.py), the room's collections (room/collect.py) and anything else of the appliance
that reads a run's logs (the 3D view replays a finished run with `read_run_log`).

They lived in the log routes; the room imported them from there. Here they sit beside the formats
they read, and every caller, route or not, uses the one definition of "the run's logs".

A run folder's contents are the loop's to make: every listing and open goes through
``runfolder.py`` (no link followed, plain files only), names are shown escaped
(``runfolder.shown``) and taken back exactly.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..runfolder import RunFolder, RunPathError, shown
from .convert import _plain
from .logformat import MAGIC
from .reader import open_log
from .timing_series import TIMING_FILE

CACHE_DIR = ".cache"  # where conversions once lived in the run folder: never listed
NOT_LOGS = ("output.txt", TIMING_FILE, "ros-bridge.txt")


def _is_log(rf: RunFolder, rel: str) -> bool:
    """xrflog by its magic; an XRF2 .bin by its two header lines (names, type codes)."""
    try:
        fd = rf.open(rel)
    except (OSError, RunPathError):
        return False
    with open(fd, "rb") as f:
        head = f.read(64 * 1024)
    if head.startswith(MAGIC):
        return True
    if not rel.endswith(".bin"):
        return False
    lines = head.split(b"\n", 2)
    return (
        len(lines) == 3
        and bool(lines[0])
        and bool(lines[1])
        and re.fullmatch(rb"[0-9 ,\r]+", lines[1]) is not None
        and b"\0" not in lines[0]
    )


def log_files(rf: RunFolder) -> list[tuple[str, os.stat_result]]:
    """(name relative to the run folder, its lstat) of each log file, oldest first: xrflog by
    content, XRF2 .bin by name; conversions (.cache/), the 3D recording and the loop's output
    are not logs. Nested folders too (an XRF2 name like /home/x/logs/log lands in
    <run>/home/x/logs/); links are neither listed nor entered (runfolder.RunFolder.walk)."""
    found = [(st.st_mtime_ns, rel, st) for rel, st in rf.walk_files(skip_top=(CACHE_DIR, "viz", *NOT_LOGS))]
    return [(rel, st) for _, rel, st in sorted(found, key=lambda x: (x[0], x[1])) if _is_log(rf, rel)]


def run_log_files(run_dir: str | Path) -> list[str]:
    """`log_files` of a run folder by its path: the names only ([] when there is no folder)."""
    try:
        rf = RunFolder(run_dir)
    except OSError:
        return []
    with rf:
        return [rel for rel, _ in log_files(rf)]


def open_run_log(rf: RunFolder, rel: str) -> Any:
    """`open_log` of a run's file through the run folder's helper: opened without following a
    link, mapped only if the loop cannot truncate it (else a private copy: open_mappable). The
    LogFile names the file by its path with the name shown escaped (names in conversions,
    messages)."""
    fd = rf.open_mappable(rel)
    try:
        return open_log(rf.path / shown(rel), fd=fd)  # mapped: stays valid after the fd is closed
    finally:
        os.close(fd)


def read_run_log(run_dir: str | Path, name: str | None = None) -> dict[str, np.ndarray]:
    """A run's log as NumPy arrays: {column: 1-D array} with `seq`, `cycle`, `t_ns` (xrflog) and
    one array per logged variable (char as uint8), plus `t` (seconds since the first record,
    float64) when the file has a clock. `name`: a file name relative to the run folder, as the
    listing shows it (default: the newest log). Raises FileNotFoundError when the run has no
    log; damaged files give every complete record (see docs/logging/decoding.md). Blocking: call
    it off the event loop."""
    try:
        rf = RunFolder(run_dir)
    except OSError:
        raise FileNotFoundError(f"{run_dir}: no run folder") from None
    with rf:
        files = [rel for rel, _ in log_files(rf)]
        if name is not None:
            files = [rel for rel in files if name in (rel, shown(rel))]
        if not files:
            raise FileNotFoundError(f"{run_dir}: no log file" + (f" named {name!r}" if name else ""))
        log = open_run_log(rf, files[-1])
    rec = log.records
    out = {col: np.array(_plain(rec[col])) for col in log.columns if col in rec.dtype.names}
    if log.kind == "xrf2":
        out["seq"] = np.arange(len(rec), dtype=np.uint64)
    if "t_ns" in out and len(out["t_ns"]):
        out["t"] = (out["t_ns"] - out["t_ns"][0]) / 1e9
    return out
