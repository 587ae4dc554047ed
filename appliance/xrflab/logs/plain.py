"""CSV and MAT of an undamaged xrflog file with the standard library only: the light conversion
child's (logs/convert_child.py; issue 30 item 4).

A download's child used to import NumPy and pyarrow (CSV) or scipy (MAT) for a job that is reading
fixed records and printing numbers: ~52-56 MB of imports in a child that runs beside the
appliance. This module reads the records with ``struct`` (the layout from rt_core through
logs/logformat.py, the header and the chain rule from logs/layout.py: the NumPy reader's own), a
window of records at a time with ``os.pread`` (nothing of the log stays in the child's memory), and
writes what logs/convert.py writes for the same log:

- CSV: the same bytes as Arrow's writer (numbers in Arrow's shortest round-trip form: ``0.00001``,
  ``1e-7``, ``1e+10``, ``-0``, ``nan``; float32 by its own shortest digits; bool and char as their
  byte's value), zipped with the change table as logs/convert.py does;
- MAT: the same variables as scipy's savemat (logs/matfile.py), a column streamed at a time.

Only a log the NumPy reader would read as whole runs of records: every segment's header parses and
every record chains into the next (layout.chain_ok), a truncated last record allowed. Anything else
(damage, an XRF2 ``.bin``, a header this reader does not know, segments that differ) is left to
logs/convert.py: ``plan`` returns None before anything is written, and the child converts as before.
"""

from __future__ import annotations

import csv
import io
import json
import math
import mmap
import operator
import os
import re
import struct
import sys
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from itertools import compress
from pathlib import Path
from typing import Any

from .layout import SECONDS_COLUMN, SegmentLayout, chain_ok, parse_segment_header
from .logformat import MAGIC, RECORD_HEADER, RECORD_HEADER_SIZE, struct_code
from .matfile import MatWriter, cell_column, char_matrix, numeric_matrix, struct_matrix

# Records read at a time (whole records, at least one): a MAT column copies a window's field out
# in C; CSV makes two Python objects a value (~100 bytes), so its windows are smaller.
WINDOW_BYTES = 1 << 20
CSV_WINDOW_BYTES = 128 << 10
# A record longer than this (the writer chose its stride; real ones are a few hundred bytes) is left
# to the NumPy reader, which maps the file: here every read is at least one whole record.
MAX_STRIDE = 64 << 10
FIND_WINDOW = 1 << 20  # bytes of the mapping searched for the next segment's magic at a time
# float32 values a CSV may have before it is left to Arrow: each takes a search over precisions
# here (f32_column), ~20x a double's time (200 000 records of 8 float32s: 8-11 s against Arrow's
# 0.5 s on this VM, several times that on a Pi). Past this a student would wait longer than the
# ~60 MB of a NumPy + Arrow child are worth: a slow download is the worse trade (session 11).
CSV_MAX_F32_VALUES = 200_000

# One row of a run's parameter change table (xrflab/params/service.py writes them; the downloads
# and GET /api/logs/runs/{id}/param-changes show them): t is the wall clock (Unix seconds).
CHANGE_COLUMNS = ("run", "cycle", "t", "name", "old", "new", "who")
CHANGES_MAT = "param_changes"  # MAT struct variable

_INT64 = 1 << 63


@dataclass(frozen=True)
class PlainSegment:
    layout: SegmentLayout
    count: int  # whole records
    lost: int  # records missing from the sequence numbers


@dataclass(frozen=True)
class Plan:
    """Where the records of an undamaged log are: what the NumPy reader would find in it."""

    fd: int
    segments: list[PlainSegment]
    skipped: int  # truncated last records (LogFile.skipped's count)

    @property
    def lost(self) -> int:
        return sum(s.lost for s in self.segments)

    @property
    def count(self) -> int:
        return sum(s.count for s in self.segments)

    @property
    def first(self) -> SegmentLayout:
        return self.segments[0].layout

    @property
    def columns(self) -> list[str]:
        """logs/convert.py's table_columns: the record header's fields, t_s, the variables."""
        return [n for n, _, _ in RECORD_HEADER] + [SECONDS_COLUMN] + list(self.first.fields)


def _header_struct(stride: int) -> struct.Struct:
    """seq, cycle, t_ns of a record (channels.h struct xrf_slot_hdr, through logformat.py)."""
    fmt, pos = "<", 0
    for _, typestr, offset in RECORD_HEADER:
        fmt += f"{offset - pos}x{struct_code(typestr)}"
        pos = offset + int(typestr[2:])
    return struct.Struct(f"{fmt}{stride - pos}x")


def _record_struct(seg: SegmentLayout) -> struct.Struct:
    """A whole record: the header's fields then every variable (at its offset), in column order."""
    fields = [(offset, typestr) for _, typestr, offset in RECORD_HEADER]
    fields += [(RECORD_HEADER_SIZE + off, vt.typestr) for off, vt in zip(seg.offsets, seg.types)]
    order = sorted(range(len(fields)), key=lambda i: fields[i][0])
    if order != list(range(len(fields))):
        raise ValueError("variables out of order")  # struct reads in file order: plan() refuses these
    fmt, pos = "<", 0
    for offset, typestr in fields:
        if offset < pos:
            raise ValueError("overlapping variables")
        fmt += f"{offset - pos}x{struct_code(typestr)}"
        pos = offset + int(typestr[2:])
    return struct.Struct(f"{fmt}{seg.stride - pos}x")


def _windows(fd: int, start: int, count: int, stride: int, window: int = WINDOW_BYTES) -> Iterator[bytes]:
    """The bytes of `count` records from `start`, whole records at a time (os.pread: nothing of
    the file is mapped or kept)."""
    per = max(1, window // stride)
    done = 0
    while done < count:
        k = min(per, count - done)
        want, off = k * stride, start + done * stride
        parts = []
        while want:
            got = os.pread(fd, want, off)
            if not got:
                raise OSError(f"the log ended at {off} while {want} more bytes were expected")
            parts.append(got)
            want -= len(got)
            off += len(got)
        yield parts[0] if len(parts) == 1 else b"".join(parts)
        done += k


def _find(mm: mmap.mmap, needle: bytes, start: int) -> int:
    """mm.find(needle, start), a window at a time, each window's pages dropped from this process
    after it was searched (they stay in the page cache): the search reads the whole file."""
    size = len(mm)
    pos = start
    while pos < size:
        stop = min(size, pos + FIND_WINDOW + len(needle) - 1)
        hit = mm.find(needle, pos, stop)
        page = pos - pos % mmap.PAGESIZE
        mm.madvise(mmap.MADV_DONTNEED, page, stop - page)
        if hit >= 0:
            return hit
        pos += FIND_WINDOW
    return -1


def plan(path: str | Path, fd: int) -> Plan | None:
    """The log open as `fd` read as the NumPy reader reads an undamaged one, or None when it is
    not one (nothing written yet: logs/convert.py then converts it)."""
    path = Path(path)
    size = os.fstat(fd).st_size
    if size < len(MAGIC) or os.pread(fd, len(MAGIC), 0) != MAGIC:
        return None  # an XRF2 .bin, or damage before the first segment
    mm = mmap.mmap(fd, size, access=mmap.ACCESS_READ)
    try:
        segments: list[PlainSegment] = []
        skipped, pos = 0, 0
        while 0 <= pos < size:
            try:
                seg = parse_segment_header(path, mm, size, pos)
                for vt in seg.types:
                    struct_code(vt.typestr)
                _record_struct(seg)
            except Exception:  # Damaged, LogFormatError, a type or layout struct cannot read
                return None  # damage, or an error the NumPy reader says in its words
            nxt = _find(mm, MAGIC, seg.data)
            end = size if nxt < 0 else nxt
            if seg.data > end or seg.stride > MAX_STRIDE:
                return None
            count, rest = divmod(end - seg.data, seg.stride)
            if not _chained(fd, seg.data, count, seg.stride):
                return None
            lost = 0
            if count >= 2:
                first = _header_struct(seg.stride).unpack_from(os.pread(fd, seg.stride, seg.data))[0]
                last = _header_struct(seg.stride).unpack_from(os.pread(fd, seg.stride, end - rest - seg.stride))[0]
                lost = last - first - (count - 1)
            skipped += 1 if rest else 0
            segments.append(PlainSegment(seg, count, lost))
            pos = nxt
        kinds = {(tuple(s.layout.fields), tuple(vt.typestr for vt in s.layout.types)) for s in segments}
        if len(kinds) != 1:
            return None  # segments that log other variables: the NumPy reader refuses them by name
        return Plan(fd, segments, skipped)
    finally:
        mm.close()


def _chained(fd: int, start: int, count: int, stride: int) -> bool:
    """Every record follows the one before it (layout.chain_ok): one run, no damage."""
    hdr = _header_struct(stride)
    last: list[tuple[int, ...]] = []  # the window before's last record
    for window in _windows(fd, start, count, stride):
        heads = last + list(hdr.iter_unpack(window))
        seq, cyc, t = zip(*heads)
        if not all(map(chain_ok, seq[:-1], cyc[:-1], t[:-1], seq[1:], cyc[1:], t[1:])):
            return False
        last = heads[-1:]
    return True


# ---- numbers as Arrow's CSV writer prints them --------------------------------------------------


def _arrow_style(text: str) -> str:
    """A shortest round-trip number (Python's repr or %e form) in Arrow's notation: plain decimal
    for decimal exponents -6..9, else d.ddde+X / d.ddde-X; no trailing ".0"."""
    if text in ("nan", "inf", "-inf"):
        return text
    neg = text.startswith("-")
    mant, _, exp = text.lstrip("-").partition("e")
    whole, _, frac = mant.partition(".")
    raw = whole + frac
    digits = raw.lstrip("0")
    point = len(whole) - (len(raw) - len(digits)) + (int(exp) if exp else 0)
    digits = digits.rstrip("0")
    sign = "-" if neg else ""
    if not digits:
        return sign + "0"
    e10 = point - 1
    if -6 <= e10 < 10:
        if point <= 0:
            return f"{sign}0.{'0' * -point}{digits}"
        if point >= len(digits):
            return sign + digits + "0" * (point - len(digits))
        return f"{sign}{digits[:point]}.{digits[point:]}"
    tail = "." + digits[1:] if len(digits) > 1 else ""
    return f"{sign}{digits[0]}{tail}e{'+' if e10 >= 0 else '-'}{abs(e10)}"


def f64_text(x: float) -> str:
    """One float64 as Arrow prints it (iter_csv does whole windows at once: arrow_numbers)."""
    return arrow_numbers(repr(x) + "\n")[:-1]


# Python's repr is the shortest round-trip too, in another notation: "1e-05", "1e+16", "100.0",
# "12345678901.5". Rewritten in CSV text, in C but for the rare exponent and >= 1e10 forms.
_EXPONENT = re.compile(r"(?<![^,\n])-?\d(?:\.\d+)?e[-+]\d+(?=[,\n])")
_LARGE = re.compile(r"(?<![^,\n])-?\d{11,}\.\d+(?=[,\n])")
_INTEGRAL = re.compile(r"\.0(?=[,\n])")


def _restyle(m: re.Match[str]) -> str:
    return _arrow_style(m.group())


def arrow_numbers(text: str, large: bool = True) -> str:
    """CSV text (lines ending in "\\n") whose floats are Python reprs, each in Arrow's notation;
    integers, "nan", "inf" and text already in Arrow's notation are left as they are. `large`:
    False when the caller knows no float in it is >= 1e10 in magnitude (that search is the slow one)."""
    if "e" in text:
        text = _EXPONENT.sub(_restyle, text)
    if large:
        text = _LARGE.sub(_restyle, text)
    return _INTEGRAL.sub("", text)


def _any_large(col: tuple[float, ...]) -> bool:
    """Whether a float column may have a value Python writes in decimal and Arrow with an exponent
    (|x| >= 1e10), in C: min and max, unless a NaN (its sum is NaN) makes them unreliable: then
    the search decides."""
    if not col:
        return False
    total = sum(col)
    return total != total or max(col) >= 1e10 or min(col) <= -1e10


def f32_column(col: tuple[float, ...]) -> list[str]:
    """float32 values (as the Python floats they widen to exactly), each by its own shortest
    digits that read back to it as float32, written as Python writes that decimal (repr of the
    double nearest it: the same digits, as it has at most 9), for arrow_numbers to restyle.

    A column at a time, in C but for the loop over precisions: every value starts at 9
    significant digits (always enough), then one digit fewer while that still reads back (if p
    digits read back, p + 1 do: the fewest is where it stops). Sensor-like values stop after
    one or two tries."""
    out = ["" for _ in col]
    todo = []
    for i, v in enumerate(col):
        if v == v and v not in (0.0, math.inf, -math.inf):
            todo.append(i)
        else:
            out[i] = repr(v)  # NaN, infinities and zeros are written as they are
    values = [col[i] for i in todo]
    want = array("f", values)
    shortest: dict[int, str] = {}
    for digits in range(8, 0, -1):
        cands = list(map(f"%.{digits - 1}e".__mod__, values))
        ok = list(map(operator.eq, array("f", map(float, cands)), want))
        if digits == 8:  # those 8 digits do not read back take 9, which always do
            shortest.update((i, f"{v:.8e}") for i, v, good in zip(todo, values, ok) if not good)
        shortest.update(zip(compress(todo, ok), compress(cands, ok)))
        todo, values = list(compress(todo, ok)), list(compress(values, ok))
        if not todo:
            break
        want = array("f", values)
    for i, text in shortest.items():
        out[i] = repr(float(text))
    return out


def f32_text(x: float) -> str:
    """One float32 as Arrow prints it (iter_csv does whole columns: f32_column)."""
    return arrow_numbers(f32_column((x,))[0] + "\n")[:-1]


def _int_column(col: tuple[Any, ...]) -> list[str]:
    return list(map(str, col))  # ints, and bool and char as their byte's value


def _f64_column(col: tuple[float, ...]) -> list[str]:
    return list(map(repr, col))  # Python's shortest round-trip: arrow_numbers restyles the window


def _text_of(typestr: str) -> Callable[[tuple[Any, ...]], list[str]]:
    """A column of values as text, in Python's notation for arrow_numbers to restyle."""
    if typestr[1] == "f":
        return _f64_column if typestr[2:] == "8" else f32_column
    return _int_column


def _seconds_of(seg: PlainSegment, fd: int) -> Callable[[int], float]:
    """t_ns -> t_s of one segment, as logs/convert.py computes it in int64 and float64:
    (t_ns - start_mono_ns) / 1e9, the difference wrapping as an int64 does."""
    start = seg.layout.header.get("start_mono_ns")
    if not isinstance(start, int):
        start = (
            _header_struct(seg.layout.stride).unpack(os.pread(fd, seg.layout.stride, seg.layout.data))[2]
            if seg.count
            else 0
        )
    if not -_INT64 <= start < _INT64:
        raise OverflowError(f"start_mono_ns {start} is not an int64")

    def seconds(t: int) -> float:
        d = t - start
        if d >= _INT64:
            d -= 1 << 64
        elif d < -_INT64:
            d += 1 << 64
        return float(d) / 1e9

    return seconds


def f32_values(p: Plan) -> int:
    """The float32 values in the log's records (what makes this module's CSV slow)."""
    per_record = sum(1 for vt in p.segments[0].layout.types if vt.typestr[1:] == "f4") if p.segments else 0
    return per_record * sum(s.count for s in p.segments)


def _starts_ok(p: Plan) -> bool:
    try:
        for seg in p.segments:
            _seconds_of(seg, p.fd)
    except OverflowError:
        return False  # NumPy fails on it: logs/convert.py says so in its words
    return True


# ---- CSV ------------------------------------------------------------------------------------------


def iter_csv(p: Plan) -> Iterator[bytes]:
    """The CSV text of the log (header row first), a window of records a chunk."""
    head = io.StringIO()
    csv.writer(head, lineterminator="\n").writerow(p.columns)
    yield head.getvalue().encode()
    nhead = len(RECORD_HEADER)
    for seg in p.segments:
        rec = _record_struct(seg.layout)
        texts = [_int_column] * nhead + [_text_of(vt.typestr) for vt in seg.layout.types]
        seconds = _seconds_of(seg, p.fd)
        t_at = [n for n, _, _ in RECORD_HEADER].index("t_ns")
        floats = [nhead + i for i, vt in enumerate(seg.layout.types) if vt.typestr[1] == "f"]
        for window in _windows(p.fd, seg.layout.data, seg.count, seg.layout.stride, CSV_WINDOW_BYTES):
            values = list(zip(*rec.iter_unpack(window)))
            cols = [f(c) for f, c in zip(texts, values)]
            t_s = tuple(map(seconds, values[t_at]))
            cols.insert(t_at + 1, _f64_column(t_s))
            large = _any_large(t_s) or any(_any_large(values[i]) for i in floats)
            yield arrow_numbers("\n".join(map(",".join, zip(*cols))) + "\n", large).encode()


def changes_csv(changes: list[dict[str, Any]]) -> str:
    """The change table as CSV text (header row first)."""
    out = io.StringIO()
    w = csv.DictWriter(out, fieldnames=CHANGE_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    w.writerows(changes)
    return out.getvalue()


class _Drain(io.RawIOBase):
    """A write-only, unseekable sink whose bytes are taken out between writes: zipfile then
    writes a streamed archive (data descriptors after each member), chunk by chunk."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        self.parts.append(bytes(b))
        return len(b)

    def take(self) -> bytes:
        out, self.parts = b"".join(self.parts), []
        return out


def csv_zip_names(stem: str, run: int | str) -> tuple[str, str]:
    """The two members of a CSV download with parameter changes: the samples, the changes."""
    return f"{stem}.csv", f"run{run}_param_changes.csv"


def zip_csv(samples: Iterator[bytes], changes: list[dict[str, Any]], names: tuple[str, str]) -> Iterator[bytes]:
    """A zip of the samples' CSV (streamed: memory bounded by one chunk) and the change table's
    CSV, as byte chunks."""
    import zipfile  # here: ~1.5 MB the child needs only for a run with parameter changes

    sink = _Drain()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open(names[0], "w", force_zip64=True) as member:
            for chunk in samples:
                member.write(chunk)
                yield sink.take()
        zf.writestr(names[1], changes_csv(changes))
        yield sink.take()
    yield sink.take()


# ---- MAT ------------------------------------------------------------------------------------------

_MATLAB_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,62}$")


def matlab_names(names: list[str], reserved: tuple[str, ...] = ()) -> list[str]:
    """Valid, unique MATLAB identifiers: other characters become `_`, a name that does not start
    with a letter gets `x` in front, at most 63 characters, clashes get `_2`, `_3`, ..."""
    taken = set(reserved)
    out = []
    for name in names:
        ident = re.sub(r"[^A-Za-z0-9_]", "_", name)
        if not ident or not ident[0].isalpha():
            ident = "x" + ident
        ident = ident[:63]
        candidate, k = ident, 2
        while candidate in taken:
            suffix = f"_{k}"
            candidate, k = ident[: 63 - len(suffix)] + suffix, k + 1
        assert _MATLAB_NAME.match(candidate)
        taken.add(candidate)
        out.append(candidate)
    return out


def _le(a: array) -> bytes:
    if sys.byteorder == "big":
        a.byteswap()
    return a.tobytes()


def _field_bytes(p: Plan, offset_of: Callable[[PlainSegment], int], size: int) -> Iterator[bytes]:
    """One field's bytes, record after record, across the segments (the log's own little-endian
    bytes: a column of the MAT file as it is in the log)."""
    for seg in p.segments:
        off, stride = offset_of(seg), seg.layout.stride
        for window in _windows(p.fd, seg.layout.data, seg.count, stride):
            out = bytearray(len(window) // stride * size)
            for j in range(size):
                out[j::size] = window[off + j :: stride]
            yield bytes(out)


def _seconds_bytes(p: Plan) -> Iterator[bytes]:
    for seg in p.segments:
        hdr, seconds = _header_struct(seg.layout.stride), _seconds_of(seg, p.fd)
        for window in _windows(p.fd, seg.layout.data, seg.count, seg.layout.stride):
            yield _le(array("d", [seconds(t) for _, _, t in hdr.iter_unpack(window)]))


def _changes_matrix(changes: list[dict[str, Any]]) -> bytes:
    """The change table as a MATLAB struct of columns (numbers as columns, text as cell arrays):
    `param_changes.name{k}` changed from `old(k)` to `new(k)` at cycle `cycle(k)` (logs/convert.py's
    _changes_struct, as scipy writes it)."""
    n = len(changes)

    def nums(key: str, code: str, typestr: str) -> bytes:
        values = [c.get(key, 0) for c in changes]
        if code == "d":
            values = [math.nan if v is None else float(v) for v in values]
        else:
            values = [int(v) for v in values]
        return numeric_matrix(typestr, (n, 1), struct.pack(f"<{n}{code}", *values))

    def text(key: str) -> bytes:
        return cell_column([str(c.get(key, "")) for c in changes])

    return struct_matrix(
        [
            ("cycle", nums("cycle", "Q", "<u8")),
            ("t", nums("t", "d", "<f8")),
            ("name", text("name")),
            ("old", nums("old", "d", "<f8")),
            ("new", nums("new", "d", "<f8")),
            ("who", text("who")),
        ],
        CHANGES_MAT,
    )


def write_mat(p: Plan, f: Any, changes: list[dict[str, Any]] | None) -> None:
    """The MAT file logs/convert.py's _to_mat writes: the record header's columns, t_s, each
    variable under its MATLAB name, ``log_header`` (every segment's header as JSON) and, with
    changes, ``param_changes``."""
    mat = MatWriter(f)
    n = p.count
    for name, typestr, offset in RECORD_HEADER:

        def header_at(s: PlainSegment, offset: int = offset) -> int:
            return offset

        mat.write_column(name, typestr, n, _field_bytes(p, header_at, int(typestr[2:])))
    mat.write_column(SECONDS_COLUMN, "<f8", n, _seconds_bytes(p))
    reserved = tuple(p.columns[: len(RECORD_HEADER) + 1]) + ("log_header", CHANGES_MAT)
    mnames = matlab_names(list(p.first.fields), reserved=reserved)
    for i, (mname, vt) in enumerate(zip(mnames, p.first.types)):
        typestr = "|u1" if vt.typestr == "|S1" else vt.typestr  # char: its byte as uint8

        def offset_of(s: PlainSegment, i: int = i) -> int:
            return RECORD_HEADER_SIZE + s.layout.offsets[i]

        mat.write_column(mname, typestr, n, _field_bytes(p, offset_of, vt.size))
    mat.write(char_matrix(json.dumps([s.layout.header for s in p.segments]), "log_header"))
    if changes is not None:
        mat.write(_changes_matrix(changes))


# ---- the child's entry ------------------------------------------------------------------------------


def convert(shown: str, fd: int, fmt: str, target: str, changes: list[dict[str, Any]], zip_names: list[str]) -> bool:
    """Write the log open as `fd` as `fmt` ("csv" or "mat") to `target` ("-": CSV to stdout after
    a line of JSON with the skipped and lost counts, as logs/convert_child.py streams it), or
    return False, having written nothing, when the log is not one this module reads."""
    p = plan(shown, fd)
    if p is None or not _starts_ok(p):
        return False
    if fmt == "csv" and f32_values(p) > CSV_MAX_F32_VALUES:
        return False  # Arrow formats float32 in C: logs/convert.py (above)
    if target == "-" and fmt == "csv":
        out = sys.stdout.buffer
        out.write(json.dumps({"skipped": p.skipped, "lost": p.lost}).encode() + b"\n")
        out.flush()
        chunks = iter_csv(p)
        if changes:
            chunks = zip_csv(chunks, changes, (zip_names[0], zip_names[1]))
        for chunk in chunks:
            out.write(chunk)
        out.flush()
        return True
    dest = Path(target)
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.part")
    try:
        with open(tmp, "wb") as f:
            if fmt == "mat":
                write_mat(p, f, changes or None)
            else:
                chunks = iter_csv(p)
                if changes:
                    chunks = zip_csv(chunks, changes, csv_zip_names(Path(shown).stem, changes[0].get("run", "")))
                for chunk in chunks:
                    f.write(chunk)
        os.replace(tmp, dest)
    finally:
        if tmp.exists():
            tmp.unlink()
    return True
