"""What xrf-watch did while the appliance was gone: its record in the run's folder, read back.

A `hold` run has a watcher process of its own (rt_core's ``xrf-watch``, started by
server/runs/watch.py's ``start_backup``) that outlives the appliance: if the appliance dies
first, it kills the loop and carries out the safe reaction (the arm held, lowered onto its rest
stops, zero). Nobody is there to hear it then, so it writes what it did as a small JSON record
into the run's folder (``RECORD``, through the folder's descriptor the appliance handed it:
rt_core/tools/watch/main.c), once when the outputs are safe and again once the arm is at rest.
The restarted appliance reads it back (server/runs/orphans.py) and keeps it with the run
(``RunRow.safe_outcome``, the Runs page).

The run folder is the guest's to write (docs/developers/security.md): the record is read like
anything a guest wrote. It is opened through ``RunFolder`` (no link followed, a plain file of
one link, made by the appliance's uid), at most ``MAX_BYTES`` are read, and every field is
checked: exactly the fields xrf-watch writes, integers in their ranges, a known reason and
phase. Anything else is refused with the reason why, which the run record says.
"""

from __future__ import annotations

import errno
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

from typing_extensions import TypedDict

from ...channels import lib
from ...runfolder import RunFolder, RunPathError
from .safety import _REASONS, WatchResult

RECORD = "xrf-watch.json"  # its name in the run folder, handed to xrf-watch (--record)
MAX_BYTES = 1024  # what xrf-watch writes is under 512 bytes

# The law's phases (xrf/hold.h XRF_HOLD_PHASE_*) by name; 0: the watcher did not hold.
PHASES = {
    0: "none",
    lib.XRF_HOLD_PHASE_HOLD: "hold",
    lib.XRF_HOLD_PHASE_CLOSING: "closing",
    lib.XRF_HOLD_PHASE_REST: "rest",
}

_I32 = (-(2**31), 2**31 - 1)
_HOUR_NS = 3600 * 10**9
# Every field xrf-watch writes, with the range a true record has.
_FIELDS: dict[str, tuple[int, int]] = {
    "xrf_watch": (1, 1),  # the record's version
    "pid": (1, 2**22),  # xrf-watch's own pid (pid_max is at most 2^22)
    "loop": (1, 2**22),
    "reason": (min(_REASONS), max(_REASONS)),
    "done": (0, 1),
    "event_unix_ms": (0, 2**53),
    "safe_after_ns": (0, _HOUR_NS),
    "rest_after_ns": (0, _HOUR_NS),
    "drop_urad": (0, _I32[1]),
    "hold_phase": (min(PHASES), max(PHASES)),
    "kill_status": (-4095, 0),
    "hold_status": (-4095, 0),
}


class SafeOutcome(TypedDict):
    """What a safety watcher did for a `hold` run (served with the run record): the run's xrf-watch
    when the appliance died, or the appliance's own watcher when the loop failed."""

    by: str  # "xrf-watch" (the appliance was gone) or "watcher" (the appliance's own)
    reason: str  # safety._REASONS' name: host_gone
    done: bool  # false: it was still lowering the arm when the record was read
    at: float  # Unix time of the fault (the appliance's death seen)
    safe_ms: float  # first safe output after the fault
    drop_deg: float  # the largest joint drop the law measured (hold)
    rest_s: float | None  # the arm at rest with the outputs zero, after the fault; None: not (yet)
    phase: str  # the law's last phase (PHASES): rest at the end of a hold
    loop_killed: bool


@dataclass(frozen=True)
class Read:
    outcome: SafeOutcome | None
    problem: str  # "" when there is an outcome or simply no record; else why it was refused
    pid: int = 0  # xrf-watch's pid while not done (to wait for it)


def parse(data: bytes) -> SafeOutcome:
    """The outcome from a record's bytes; ValueError saying why they are not a true record."""
    try:
        raw = json.loads(data.decode("ascii"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"not a JSON record ({exc.__class__.__name__})") from None
    if not isinstance(raw, dict) or set(raw) != set(_FIELDS):
        raise ValueError("not xrf-watch's fields")
    for name, (lo, hi) in _FIELDS.items():
        v = raw[name]
        if type(v) is not int or not lo <= v <= hi:  # bool is not an int here
            raise ValueError(f"{name} out of range")
    if raw["reason"] not in _REASONS or raw["hold_phase"] not in PHASES:
        raise ValueError("unknown reason or phase")
    rest = raw["rest_after_ns"]
    return SafeOutcome(
        by="xrf-watch",
        reason=_REASONS[raw["reason"]],
        done=bool(raw["done"]),
        at=raw["event_unix_ms"] / 1000,
        safe_ms=round(raw["safe_after_ns"] / 1e6, 3),
        drop_deg=round(math.degrees(raw["drop_urad"] / 1e6), 3),
        rest_s=round(rest / 1e9, 3) if rest else None,
        phase=PHASES[raw["hold_phase"]],
        loop_killed=raw["kill_status"] == 0,
    )


def of_watch(result: WatchResult) -> SafeOutcome | None:
    """The appliance's own watcher's outcome of a loop that failed during a `hold` run (its last
    result: xrf_watch_stop waits for the closing sequence); None where it held nothing."""
    if not result.acted or result.hold_phase not in PHASES or result.hold_phase == 0:
        return None
    ago_s = (time.monotonic_ns() - result.event_ns) / 1e9
    return SafeOutcome(
        by="watcher",
        reason=result.reason,
        done=True,
        at=round(time.time() - ago_s, 3),
        safe_ms=round(result.reaction_ms, 3),
        drop_deg=round(math.degrees(max(0, result.drop_urad) / 1e6), 3),
        rest_s=round((result.rest_ns - result.event_ns) / 1e9, 3) if result.rest_ns else None,
        phase=PHASES[result.hold_phase],
        loop_killed=result.kill_status == 0,
    )


def read(run_dir: str | Path) -> Read:
    """The record in `run_dir`, if any: never a link followed, never more than MAX_BYTES read,
    never a file the appliance's uid did not make."""
    try:
        with RunFolder(run_dir) as rf:
            fd = rf.open(RECORD, own=True)
    except FileNotFoundError:
        return Read(None, "")
    except (OSError, RunPathError) as exc:
        if getattr(exc, "errno", 0) == errno.ENOENT:
            return Read(None, "")
        return Read(None, f"{RECORD} refused: {exc}")
    try:
        data = _read_at_most(fd, MAX_BYTES + 1)
    except OSError as exc:
        return Read(None, f"{RECORD} unreadable: {exc}")
    finally:
        os.close(fd)
    if len(data) > MAX_BYTES:
        return Read(None, f"{RECORD} refused: over {MAX_BYTES} bytes")
    try:
        outcome = parse(data)
    except ValueError as exc:
        return Read(None, f"{RECORD} refused: {exc}")
    pid = 0 if outcome["done"] else int(json.loads(data)["pid"])
    return Read(outcome, "", pid)


def _read_at_most(fd: int, n: int) -> bytes:
    chunks: list[bytes] = []
    while n > 0:
        chunk = os.read(fd, min(n, 4096))
        if not chunk:
            break
        chunks.append(chunk)
        n -= len(chunk)
    return b"".join(chunks)


def describe(o: SafeOutcome) -> str:
    """One sentence for the run record's message."""
    killed = "killed the loop and " if o["loop_killed"] else ""
    who = "its xrf-watch" if o["by"] == "xrf-watch" else "the safety watcher"
    text = f"{who} {killed}made the outputs safe {o['safe_ms']:.2f} ms after"
    if o["phase"] != "none":
        text += f"; the arm held (largest joint drop {o['drop_deg']:.2f}°)"
        if o["rest_s"] is not None:
            text += f", lowered onto its rest stops, at rest {o['rest_s']:.1f} s after"
        else:
            text += f", not at rest yet when read (phase {o['phase']})"
    return text
