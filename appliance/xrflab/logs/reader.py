"""Reading `xrflog` files (docs/logging/file-format.md) into NumPy structured arrays.

The file is mapped, never read into Python objects: each run of good records is one
`np.ndarray` view over the mapping (stride = the segment's record stride), so a million-record
file opens in milliseconds and costs no memory until columns are touched. Damage is handled per
segment: a truncated last record, bytes that are not records (garbage appended or inserted),
a segment header that does not parse; every complete record that can be found is kept and
`LogFile.skipped` says, in words, what was not. Things a reader cannot guess (an unknown
format version or variable type code) raise `LogFormatError` naming the file.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# A segment's header, column names and the chain rule, without NumPy (logs/plain.py reads them
# too); LogFormatError and SECONDS_COLUMN are re-exported from here for the callers.
from .layout import (
    SECONDS_COLUMN,  # noqa: F401
    Damaged,
    LogFormatError,
    chain_ok,
    field_names,
    logged_names,
    parse_segment_header,
    var_types,
)

# The format's magic, prefix layout and type table: rt_core's logformat.h, through cffi.
# seq, cycle, t_ns: the record header (channels.h struct xrf_slot_hdr) likewise.
from .logformat import MAGIC, RECORD_HEADER, RECORD_HEADER_SIZE, VAR_TYPES

# The most record bytes LogFile.iter_chunks hands out at once (a chunk's columns, and what a
# converter makes of them, are a few times this).
CHUNK_BYTES = 4 << 20

# Resynchronising after damage scans byte offsets in windows of this many bytes, so its cost
# is proportional to the damage, not to the rest of the file.
RESYNC_WINDOW = 1 << 20


@dataclass(frozen=True)
class Variable:
    name: str  # as logged (addVariable's name)
    field: str  # the NumPy field / output column name (unique; see layout.field_names)
    code: int  # XRF2 type code
    dtype: np.dtype
    offset: int  # from the start of the payload

    @property
    def type_name(self) -> str:
        return VAR_TYPES[self.code].name


@dataclass
class Segment:
    """One run of the logger: its header and its decoded records."""

    index: int
    offset: int  # file offset of the segment's first byte
    header: dict[str, Any]
    variables: tuple[Variable, ...]
    records: np.ndarray  # structured; a view over the file when undamaged
    kind: str = "xrflog"  # or "xrf2" (no seq/cycle/t_ns in the file)

    def column(self, name: str) -> np.ndarray:
        """A field of the records; for XRF2 files `seq` is the synthesized record index."""
        if name == "seq" and "seq" not in (self.records.dtype.names or ()):
            return np.arange(len(self.records), dtype=np.uint64)
        return self.records[name]

    @property
    def has_clock(self) -> bool:
        return "t_ns" in (self.records.dtype.names or ())

    def wall_ns(self, t_ns: np.ndarray) -> np.ndarray:
        """CLOCK_MONOTONIC stamps to Unix nanoseconds (file-format.md: start_unix - start_mono + t)."""
        shift = int(self.header.get("start_unix_ns", 0)) - int(self.header.get("start_mono_ns", 0))
        return t_ns.astype(np.int64) + np.int64(shift)

    @property
    def lost(self) -> int:
        if self.kind != "xrflog" or len(self.records) < 2:
            return 0
        gaps = np.diff(self.records["seq"])
        return int((gaps - 1).sum()) if len(gaps) else 0


@dataclass
class LogFile:
    path: Path
    kind: str  # "xrflog" or "xrf2"
    segments: list[Segment] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    size: int = 0

    @property
    def lost(self) -> int:
        """Records missing from the sequence numbers (ring overflow or records destroyed by damage)."""
        return sum(s.lost for s in self.segments)

    @property
    def skipped_bytes(self) -> int:
        return self._skipped_bytes

    _skipped_bytes: int = 0

    def note_skipped(self, what: str, length: int) -> None:
        """Bytes the reader of this file's format could not use: said in words, counted."""
        self.skipped.append(what)
        self._skipped_bytes += length

    @property
    def variables(self) -> tuple[Variable, ...]:
        return self.segments[0].variables if self.segments else ()

    @property
    def columns(self) -> list[str]:
        """Output column names, in order: the record header fields then the variables."""
        if not self.segments:
            return []
        head = ["seq", "cycle", "t_ns"] if self.kind == "xrflog" else ["seq"]
        return head + [v.field for v in self.variables]

    def __len__(self) -> int:
        return sum(len(s.records) for s in self.segments)

    def check_uniform(self) -> None:
        """Raise unless every segment logs the same variables (names and types), in order."""
        if not self.segments:
            return
        first = [(v.field, v.dtype) for v in self.segments[0].variables]
        for s in self.segments[1:]:
            if [(v.field, v.dtype) for v in s.variables] != first:
                raise LogFormatError(
                    f"{self.path}: segment {s.index} (offset {s.offset}) logs other variables "
                    f"than segment 0; decode the segments separately (LogFile.segments)"
                )

    @property
    def records(self) -> np.ndarray:
        """All segments' records as one array (a view when there is a single undamaged run)."""
        if not self.segments:
            return np.empty(0, dtype=np.dtype([(n, f) for n, f, _ in RECORD_HEADER]))
        if len(self.segments) == 1:
            return self.segments[0].records
        dtypes = {s.records.dtype for s in self.segments}
        if len(dtypes) != 1:
            self.check_uniform()  # names the segment that differs
            # Same variables at other offsets: repack each into the first segment's layout.
            base = self.segments[0].records.dtype
            return np.concatenate([_repack(s.records, base) for s in self.segments])
        return np.concatenate([s.records for s in self.segments])

    # The file's mapping (open_log), for release_pages.
    _mapping: Any = None

    def release_pages(self) -> None:
        """Drop the file's pages read so far from this process's memory (its RSS): they stay in
        the page cache and are read again from there if touched. A conversion walks the whole
        file once, and every page it read counted in its RSS to the end: a child converting a
        70 MB log grew by 70 MB (issue 30 item 4)."""
        if isinstance(self._mapping, mmap.mmap):
            self._mapping.madvise(mmap.MADV_DONTNEED)

    def iter_chunks(self, rows: int = 65536) -> Iterator[tuple[Segment, dict[str, np.ndarray]]]:
        """(segment, {column: array}) for at most `rows` records and CHUNK_BYTES of them at a
        time: bounded memory, whatever the file's length or record size (the pages of each
        chunk are released once the next is asked for)."""
        self.check_uniform()
        for seg in self.segments:
            rows = max(1, min(rows, CHUNK_BYTES // max(1, seg.records.dtype.itemsize)))
            for start in range(0, len(seg.records), rows):
                self.release_pages()
                part = seg.records[start : start + rows]
                cols: dict[str, np.ndarray] = {}
                if self.kind == "xrflog":
                    for name in ("seq", "cycle", "t_ns"):
                        cols[name] = part[name]
                else:
                    cols["seq"] = np.arange(start, start + len(part), dtype=np.uint64)
                for v in seg.variables:
                    cols[v.field] = part[v.field]
                yield seg, cols

    def summary(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "kind": self.kind,
            "size": self.size,
            "records": len(self),
            "segments": [
                {
                    "offset": s.offset,
                    "records": len(s.records),
                    "lost": s.lost,
                    "program": s.header.get("program"),
                    "cycle_freq": s.header.get("cycle_freq"),
                }
                for s in self.segments
            ],
            "variables": [{"name": v.name, "column": v.field, "type": v.type_name} for v in self.variables],
            "lost": self.lost,
            "skipped_bytes": self.skipped_bytes,
            "skipped": list(self.skipped),
        }


def _repack(records: np.ndarray, dtype: np.dtype) -> np.ndarray:
    out = np.zeros(len(records), dtype=dtype)
    for name in dtype.names or ():
        out[name] = records[name]
    return out


def make_variables(
    path: Path, names: list[str], codes: list[int], offsets: list[int] | None, reserved: tuple[str, ...]
) -> tuple[Variable, ...]:
    """Validate type codes and build the variables (packed offsets when none are given); names
    as layout.logged_names keeps them."""
    names = logged_names(names)
    fields = field_names(names, reserved)
    out, pos = [], 0
    for i, (name, vt) in enumerate(zip(names, var_types(path, names, codes))):
        off = offsets[i] if offsets is not None else pos
        out.append(Variable(name, fields[i], vt.code, vt.dtype, off))
        pos = off + vt.dtype.itemsize
    return tuple(out)


def record_dtype(variables: tuple[Variable, ...], stride: int, header: bool = True) -> np.dtype:
    names: list[str] = []
    formats: list[str | np.dtype] = []
    offsets: list[int] = []
    base = 0
    if header:
        for n, f, offset in RECORD_HEADER:
            names.append(n)
            formats.append(f)
            offsets.append(offset)
        base = RECORD_HEADER_SIZE
    for v in variables:
        names.append(v.field)
        formats.append(v.dtype)
        offsets.append(base + v.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": stride})


class _Mapped:
    """The file's bytes, memory-mapped (an empty file has nothing to map). From `fd` when given
    (a file opened by the caller, e.g. in a run folder by runfolder.open_mappable), else by path."""

    def __init__(self, path: Path, fd: int | None = None) -> None:
        if fd is not None:
            size = os.fstat(fd).st_size
            self.buf: Any = mmap.mmap(fd, size, access=mmap.ACCESS_READ) if size else b""
        else:
            with open(path, "rb") as f:
                size = f.seek(0, 2)
                self.buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
        self.size = size

    def find(self, needle: bytes, start: int) -> int:
        return self.buf.find(needle, start)

    def u64_at_each_byte(self, start: int, count: int) -> np.ndarray:
        """uint64 read at every byte offset start..start+count-1 (unaligned strided view)."""
        return np.ndarray((max(count, 0),), dtype="<u8", buffer=self.buf, offset=start, strides=(1,))

    def i64_at_each_byte(self, start: int, count: int) -> np.ndarray:
        return np.ndarray((max(count, 0),), dtype="<i8", buffer=self.buf, offset=start, strides=(1,))


def _parse_segment_header(path: Path, m: _Mapped, pos: int) -> tuple[dict[str, Any], tuple[Variable, ...], int, int]:
    """(header, variables, stride, data offset) of the segment whose magic is at `pos`
    (layout.parse_segment_header: Damaged or LogFormatError)."""
    seg = parse_segment_header(path, m.buf, m.size, pos)
    variables = tuple(
        Variable(name, fld, vt.code, vt.dtype, off)
        for name, fld, vt, off in zip(seg.names, seg.fields, seg.types, seg.offsets)
    )
    return seg.header, variables, seg.stride, seg.data


def _chain_ok(seq0, cyc0, t0, seq1, cyc1, t1):
    """layout.chain_ok, vectorised (an unsigned step below zero wraps: see there)."""
    with np.errstate(over="ignore"):
        return chain_ok(seq0, cyc0, t0, seq1, cyc1, t1)


class _SegmentScanner:
    """Finds the runs of good records in [start, end) of one segment (see module docstring)."""

    def __init__(self, m: _Mapped, stride: int, dtype: np.dtype) -> None:
        self.m, self.stride, self.dtype = m, stride, dtype
        self.hdr_dtype = np.dtype(
            {
                "names": ["seq", "cycle", "t_ns"],
                "formats": ["<u8", "<u8", "<i8"],
                "offsets": [0, 8, 16],
                "itemsize": stride,
            }
        )

    def _headers(self, pos: int, n: int) -> np.ndarray:
        return np.ndarray((n,), dtype=self.hdr_dtype, buffer=self.m.buf, offset=pos)

    def _resync(self, pos: int, end: int, last: tuple[int, int, int] | None) -> int | None:
        """First byte offset >= pos where a record plausibly continues `last` and is followed by
        a record that continues it (when there is room for one)."""
        S = self.stride
        a = pos
        while a + RECORD_HEADER_SIZE <= end:
            # One stride more than the step, so every hit's competitors (below) are in view.
            count = min(RESYNC_WINDOW + S, end - RECORD_HEADER_SIZE + 1 - a)
            seq = self.m.u64_at_each_byte(a, count)
            cyc = self.m.u64_at_each_byte(a + 8, count)
            t = self.m.i64_at_each_byte(a + 16, count)
            if last is not None:
                ok = _chain_ok(np.uint64(last[0]), np.uint64(last[1]), np.int64(last[2]), seq, cyc, t)
            else:
                ok = np.ones(count, dtype=bool)
            # Candidates with a whole following record must chain into it too; a candidate
            # near the end (no room for a follower) is only accepted when `last` vouches for it.
            room = (np.arange(count) + a + 2 * S) <= end
            k = int(room.sum())  # offsets with room form a prefix
            if k:
                nxt = _chain_ok(
                    seq[:k],
                    cyc[:k],
                    t[:k],
                    self.m.u64_at_each_byte(a + S, k),
                    self.m.u64_at_each_byte(a + S + 8, k),
                    self.m.i64_at_each_byte(a + S + 16, k),
                )
                ok[:k] &= nxt
            if last is None:
                ok[k:] = False
            ok &= (np.arange(count) + a + S) <= end  # the record itself must be complete
            hits = np.flatnonzero(ok)
            if len(hits) and hits[0] < RESYNC_WINDOW:
                # Reading a good run one byte early or late also looks like a chained run (seq
                # shifted by 8 bits, a little-endian neighbour's byte below): of the hits within
                # one stride, the true record boundary is the one with the smallest seq.
                near = hits[hits < hits[0] + S]
                return a + int(near[np.argmin(seq[near])])
            a += RESYNC_WINDOW
        return None

    def scan(self, start: int, end: int) -> tuple[list[tuple[int, int]], list[tuple[int, int, str]]]:
        """(runs as (offset, count), skipped regions as (offset, length, why))."""
        S = self.stride
        runs: list[tuple[int, int]] = []
        skipped: list[tuple[int, int, str]] = []
        pos, last = start, None
        while pos + S <= end:
            n = (end - pos) // S
            h = self._headers(pos, n)
            seq, cyc, t = h["seq"], h["cycle"], h["t_ns"]
            chain = _chain_ok(seq[:-1], cyc[:-1], t[:-1], seq[1:], cyc[1:], t[1:])
            if last is not None:
                first_ok = bool(
                    _chain_ok(np.uint64(last[0]), np.uint64(last[1]), np.int64(last[2]), seq[0], cyc[0], t[0])
                )
            else:
                first_ok = n == 1 or bool(chain[0])
            if not first_ok:
                found = self._resync(pos + 1, end, last)
                stop = end if found is None else found
                if found is None and last is not None and end - pos < S:
                    break
                skipped.append((pos, stop - pos, "bytes that are not records"))
                if found is None:
                    return runs, skipped
                pos = found
                continue
            breaks = np.flatnonzero(~chain)
            k = int(breaks[0]) + 1 if len(breaks) else n
            runs.append((pos, k))
            last = (int(seq[k - 1]), int(cyc[k - 1]), int(t[k - 1]))
            pos += k * S
        if pos < end:
            skipped.append((pos, end - pos, "truncated last record"))
        return runs, skipped


def _read_xrflog(path: Path, m: _Mapped, log: LogFile) -> None:
    pos = m.find(MAGIC, 0)
    if pos > 0:
        log.note_skipped(f"offset 0: {pos} bytes before the first segment magic skipped", pos)
    while 0 <= pos < m.size:
        try:
            header, variables, stride, data = _parse_segment_header(path, m, pos)
        except Damaged as exc:
            nxt = m.find(MAGIC, pos + 1)
            stop = m.size if nxt < 0 else nxt
            log.note_skipped(f"offset {pos}: damaged segment header ({exc}); {stop - pos} bytes skipped", stop - pos)
            pos = nxt
            continue
        # A segment's records run to the next magic: an appending writer starts the next run
        # right after the last (possibly partial) record of the previous one.
        nxt = m.find(MAGIC, data)
        end = m.size if nxt < 0 else nxt
        dtype = record_dtype(variables, stride)
        runs, bad = _SegmentScanner(m, stride, dtype).scan(min(data, end), end)
        for off, length, why in bad:
            log.note_skipped(f"offset {off}: {why}, {length} bytes skipped (segment {len(log.segments)})", length)
        views = [np.ndarray((count,), dtype=dtype, buffer=m.buf, offset=off) for off, count in runs]
        if not views:
            records = np.empty(0, dtype=dtype)
        elif len(views) == 1:
            records = views[0]
        else:
            records = np.concatenate(views)
        log.segments.append(Segment(len(log.segments), pos, header, variables, records))
        pos = nxt


# A log format besides xrflog: (path, the mapped file, its size) -> its LogFile, or None when the
# file does not start like one of its kind.
FormatReader = Callable[[Path, Any, int], "LogFile | None"]
_other_formats: list[FormatReader] = []


# The modules of the other formats (of this package), imported by open_log's first call: each
# registers itself (register_format) as it is imported. Not by the package's __init__, which imports
# nothing (the light conversion child, logs/plain.py, must not load NumPy).
FORMAT_MODULES = ("xrf2bin",)


def register_format(read: FormatReader) -> None:
    """Add a format open_log recognises by content. A format's module registers itself when it is
    imported (xrf2bin.py), and open_log imports FORMAT_MODULES first, so the reader knows none of
    them but by their module's name."""
    if read not in _other_formats:
        _other_formats.append(read)


def _import_formats() -> None:
    import importlib

    for name in FORMAT_MODULES:
        importlib.import_module(f".{name}", __package__)


def open_log(path: str | Path, fd: int | None = None) -> LogFile:
    """Open an xrflog file or a file of a registered format, e.g. XRF2's `.bin` (recognised by
    content, not by name). `fd`: read that open file instead (`path` then only names it in the
    LogFile and in messages); the mapping stays valid after the caller closes it."""
    _import_formats()
    path = Path(path)
    m = _Mapped(path, fd)
    if m.size >= len(MAGIC) and bytes(m.buf[: len(MAGIC)]) == MAGIC:
        log = LogFile(path, "xrflog", size=m.size)
        _read_xrflog(path, m, log)
        log._mapping = m.buf
        return log
    for read in _other_formats:
        other = read(path, m.buf, m.size)
        if other is not None:
            other._mapping = m.buf
            return other
    if m.size and m.find(MAGIC, 0) >= 0:  # damaged start, but segments further on
        log = LogFile(path, "xrflog", size=m.size)
        _read_xrflog(path, m, log)
        log._mapping = m.buf
        return log
    raise LogFormatError(
        f"{path}: neither an xrflog file (no {MAGIC!r} magic) nor an XRF2 .bin file "
        f"(two text header lines: names, type codes)"
    )
