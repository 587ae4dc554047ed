"""Per-run telemetry recording for the 3D view's replay.

The loop's own log (xrflab.logs) holds the variables a program logs, not the encoder counts, so
the appliance keeps its own compact recording of every run, written from the telemetry the
supervisor's reader already takes (nothing is added to the loop):

    <run_dir>/viz/meta.json        {"format": 2, "channels": n, "record": "<qI{n}H", "plant", "profile", ...}
    <run_dir>/viz/telemetry.bin    fixed records: t_ns (int64), cycle (uint32), enc[n] (uint16)

n is the bench's channel count (the run's shared-memory header: 4 on one ico board, 9 on the
youBot), so the replay moves every joint and wheel the run drove. Format 1 (before benches had a
count) is "<qI4H" and still reads. The loop can rewrite meta.json: its `channels` is bounded
(1..XRF_MAX_CHANNELS) and the record layout is derived from it, never taken from "record".
    <run_dir>/viz/events.jsonl     {"t_ns": .., "setpoint": {...}} / {"t_ns": .., "reset_odometry": true}

The run folder is the loop's to write too (it can rename viz/, put a link or a FIFO in its place):
every file here is opened, written and read through the run folder's helper
(``runfolder.py``): nothing is followed, meta.json is rewritten as a new file renamed over
the old name (never written through what the loop put there), reads are bounded.

At most one sample per ``min_period_s`` (5 ms: 200 Hz, 4 kB/s on 4 channels, 6 kB/s on 9) is kept; a slower loop has every
sample kept. That is fast enough to unwrap the 14-bit counters (a shaft would have to turn two
motor revolutions in 5 ms to be misread) and small enough to keep for every run. The raw counts
are recorded, not angles: a corrected profile replays an old run correctly.
"""

from __future__ import annotations

import json
import os
import stat
import struct
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..profiles import max_channels
from ..runfolder import RunFolder, RunPathError

FORMAT = 2
FORMAT_4CH = 1  # a recording from before the channel count: always 4 encoders
SUBDIR = "viz"
META, TELEMETRY, EVENTS = f"{SUBDIR}/meta.json", f"{SUBDIR}/telemetry.bin", f"{SUBDIR}/events.jsonl"
# What a replay reads at most (200 samples/s of 20 bytes is 14 MB an hour: 256 MB is 18 hours;
# 9 channels, 30 bytes: 12 hours).
MAX_META = 1 << 20
MAX_TELEMETRY = 256 << 20
MAX_EVENTS = 64 << 20
_APPEND = os.O_WRONLY | os.O_CREAT | os.O_APPEND


def recording_dir(run_dir: Path | str) -> Path:
    return Path(run_dir) / SUBDIR


def record_struct(channels: int) -> struct.Struct:
    """One sample's record on a bench of `channels` encoders (ValueError outside 1..XRF_MAX_CHANNELS)."""
    if isinstance(channels, bool) or not isinstance(channels, int) or not 1 <= channels <= max_channels():
        raise ValueError(f"a recording has 1..{max_channels()} channels, not {channels!r}")
    return struct.Struct(f"<qI{channels}H")


class Recorder:
    """Writes one run's recording. Not thread-safe: called from the appliance's event loop only."""

    def __init__(
        self,
        run_dir: Path | str,
        meta: dict[str, Any],
        channels: int = 4,
        min_period_s: float = 0.005,
        flush_period_s: float = 1.0,
    ) -> None:
        """`channels`: the bench's count (the run's shared-memory header); a sample with fewer
        encoders is padded with 0, extra ones are not recorded."""
        self.record = record_struct(channels)
        self.channels = channels
        self.dir = recording_dir(run_dir)
        Path(run_dir).mkdir(parents=True, exist_ok=True)  # the appliance's path (tests: a fresh one)
        self._folder = RunFolder(run_dir)
        self.min_period_ns = int(min_period_s * 1e9)
        self.flush_period_s = flush_period_s
        self.meta = {
            **meta,
            "format": FORMAT,
            "channels": channels,
            "record": self.record.format,
            "min_period_s": min_period_s,
            "created": time.time(),
        }
        try:
            self._folder.replace(META, self._meta_bytes())
            self._bin = open(self._folder.open(TELEMETRY, os.O_WRONLY | os.O_CREAT, own=True, truncate=True), "wb")
            try:
                self._events = open(self._folder.open(EVENTS, _APPEND, own=True), "a", encoding="utf-8")
            except BaseException:
                self._bin.close()
                raise
        except BaseException:
            self._folder.close()
            raise
        self._last_kept_ns: int | None = None
        self._pending: tuple[int, int, tuple[int, ...]] | None = None  # newest sample not kept
        self._last_flush = time.monotonic()
        self.samples = 0
        self.last_t_ns = 0
        self.closed = False

    def add(self, t_ns: int, cycle: int, enc: Sequence[int]) -> bool:
        """Offer one sample; True if it was kept (the caller feeds kept samples to the live view,
        so live and replay see the same samples)."""
        if self.closed:
            return False
        self.last_t_ns = t_ns
        if self._last_kept_ns is not None and t_ns - self._last_kept_ns < self.min_period_ns:
            self._pending = (t_ns, cycle, tuple(enc))
            return False
        self._write(t_ns, cycle, enc)
        return True

    def add_many(self, t_ns: np.ndarray, cycle: np.ndarray, enc: np.ndarray) -> bool:
        """`add` for a whole batch (numpy columns: t_ns, cycle, enc as samples x channels) when
        every sample of it would be kept (spaced at least `min_period_s`, as a RELbot's 50 a
        second are at 200 Hz): then they are written with one pack and True is returned. False,
        with nothing written, for a batch that is denser than that (or a closed recording): offer
        its samples one by one with `add`. The bytes are the same as `add`'s."""
        k = len(t_ns)
        if self.closed or k == 0:
            return False
        t = np.asarray(t_ns, dtype=np.int64)
        if self._last_kept_ns is not None and int(t[0]) - self._last_kept_ns < self.min_period_ns:
            return False
        if k > 1 and int(np.diff(t).min()) < self.min_period_ns:
            return False
        n = self.channels
        rows = np.zeros(k, dtype=np.dtype([("t", "<i8"), ("c", "<u4"), ("e", "<u2", (n,))]))
        rows["t"] = t
        rows["c"] = np.asarray(cycle, dtype=np.int64) & 0xFFFFFFFF
        m = min(n, enc.shape[1])
        rows["e"][:, :m] = np.asarray(enc[:, :m], dtype=np.int64) & 0xFFFF  # fewer channels: 0, as add pads
        self._bin.write(rows.tobytes())
        self.last_t_ns = self._last_kept_ns = int(t[-1])
        self._pending = None
        self.samples += k
        if time.monotonic() - self._last_flush >= self.flush_period_s:
            self.flush()
        return True

    def _write(self, t_ns: int, cycle: int, enc: Sequence[int]) -> None:
        n = self.channels
        counts = [int(e) & 0xFFFF for e in enc[:n]]
        self._bin.write(self.record.pack(t_ns, cycle & 0xFFFFFFFF, *counts, *([0] * (n - len(counts)))))
        self._last_kept_ns = t_ns
        self._pending = None
        self.samples += 1
        now = time.monotonic()
        if now - self._last_flush >= self.flush_period_s:
            self.flush()

    def event(self, t_ns: int, **fields: Any) -> None:
        if self.closed:
            return
        self._events.write(json.dumps({"t_ns": t_ns, **fields}, allow_nan=False, default=str) + "\n")
        self._events.flush()

    def flush(self) -> None:
        self._bin.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if self.closed:
            return
        if self._pending is not None:  # the run's last position, even if it came < 5 ms after
            self._write(*self._pending)
        self.closed = True
        self._bin.close()
        self._events.close()
        self.meta["samples"] = self.samples
        self.meta["closed"] = time.time()
        try:
            self._folder.replace(META, self._meta_bytes())
        except (OSError, RunPathError):
            pass  # the loop took viz/ away (or put a link there): its recording ends unclosed
        finally:
            self._folder.close()

    def _meta_bytes(self) -> bytes:
        return (json.dumps(self.meta, indent=1) + "\n").encode()


@dataclass
class Recording:
    meta: dict[str, Any]
    t_ns: list[int]
    cycle: list[int]
    enc: list[tuple[int, ...]]  # the bench's channel count per sample (meta["channels"])
    events: list[dict[str, Any]] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return (self.t_ns[-1] - self.t_ns[0]) / 1e9 if self.t_ns else 0.0

    def __len__(self) -> int:
        return len(self.t_ns)


def recording_size(run_dir: Path | str) -> int | None:
    """Bytes of the run's telemetry recording, None if it has none (plain files only)."""
    try:
        with RunFolder(run_dir) as rf:
            if not rf.is_file(META):
                return None
            st = rf.lstat(TELEMETRY)
    except (OSError, RunPathError):
        return None
    return st.st_size if stat.S_ISREG(st.st_mode) and st.st_nlink == 1 else None


def has_recording(run_dir: Path | str) -> bool:
    return recording_size(run_dir) is not None


def load_recording(run_dir: Path | str) -> Recording:
    """Read a run's recording (FileNotFoundError if there is none; OSError if a file is not a
    plain one of the run or too large). A torn last record (the appliance died mid-write) is
    ignored."""
    d = recording_dir(run_dir)
    with RunFolder(run_dir) as rf:
        try:
            meta = json.loads(rf.read_bytes(META, MAX_META))
        except RecursionError:  # a meta.json the loop wrote: 1 MB of '['
            raise ValueError(f"{d}: meta.json is nested too deep") from None
        fmt = meta.get("format") if isinstance(meta, dict) else meta
        if fmt == FORMAT_4CH:
            record = record_struct(4)
        elif fmt == FORMAT:
            record = record_struct(meta.get("channels"))  # ValueError: not 1..XRF_MAX_CHANNELS
        else:
            raise ValueError(f"{d}: recording format {fmt!r} is not known")
        data = rf.read_bytes(TELEMETRY, MAX_TELEMETRY)
        try:
            event_bytes = rf.read_bytes(EVENTS, MAX_EVENTS)
        except FileNotFoundError:
            event_bytes = b""
    n = len(data) // record.size
    t_ns: list[int] = []
    cycle: list[int] = []
    enc: list[tuple[int, ...]] = []
    for t, c, *e in record.iter_unpack(data[: n * record.size]):
        t_ns.append(t)
        cycle.append(c)
        enc.append(tuple(e))
    events: list[dict[str, Any]] = []
    for line in event_bytes.decode("utf-8", "replace").splitlines():
        try:
            ev = json.loads(line)
        except (json.JSONDecodeError, RecursionError):
            continue  # a torn last line (or one the loop wrote)
        if isinstance(ev, dict) and isinstance(ev.get("t_ns"), int):
            events.append(ev)
    events.sort(key=lambda e: e["t_ns"])
    return Recording(meta, t_ns, cycle, enc, events)


def write_recording(
    run_dir: Path | str,
    meta: dict[str, Any],
    samples: Iterable[tuple[int, Sequence[int]]],
    events: Iterable[dict[str, Any]] = (),
    channels: int = 4,
) -> Path:
    """A recording from (t_ns, enc) pairs, every sample kept (tests, converted data)."""
    rec = Recorder(run_dir, meta, channels, min_period_s=0.0)
    for i, (t, enc) in enumerate(samples):
        rec.add(t, i, enc)
    for ev in events:
        ev = dict(ev)
        rec.event(int(ev.pop("t_ns")), **ev)
    rec.close()
    return rec.dir
