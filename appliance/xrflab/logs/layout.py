"""What an xrflog segment is, in the standard library only: its header parsed and checked, its
column names, and the rule by which one record may follow another.

Both readers use it: the NumPy reader (logs/reader.py, every format and every kind of damage) and
the light conversion child's (logs/plain.py, CSV and MAT of an undamaged log without NumPy), so the
two cannot disagree on a header, a name or a chain. The byte layout itself is rt_core's
(logs/logformat.py, through cffi).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import Invalid
from .logformat import (
    ALIGN,
    FORMAT_VERSION,
    JSON_LEN_OFFSET,
    PREFIX_SIZE,
    RECORD_HEADER,
    RECORD_HEADER_SIZE,
    STRIDE_OFFSET,
    VAR_TYPES,
    VarType,
)

# The derived column the tabular formats add after t_ns (logs/convert.py: seconds from the run's
# start); reserved like the header's names so a variable called t_s becomes t_s_2, not a clash.
SECONDS_COLUMN = "t_s"
# A JSON header longer than this is taken as damage, not as a header (100 variables need ~8 KB).
MAX_HEADER_BYTES = 1 << 20
# Two consecutive good records differ in seq by 1 plus the records lost between them. A
# bigger jump than this is not loss but bytes that are not a record (random data has a
# 1 - 2**-24 chance of failing the test).
MAX_SEQ_JUMP = 1 << 40
# Names a variable of an xrflog segment cannot take as its column (it gets `_2`).
XRFLOG_RESERVED = tuple(n for n, _, _ in RECORD_HEADER) + (SECONDS_COLUMN,)


class LogFormatError(Invalid, ValueError):
    """A file that cannot be decoded at all: not a log file, an unknown version or type code.
    An XrfError (422): a request for such a file is answered with this message."""


class Damaged(Exception):
    """A segment header that does not parse: skipped, and said so, rather than raised."""


def chain_ok(seq0: Any, cyc0: Any, t0: Any, seq1: Any, cyc1: Any, t1: Any) -> Any:
    """Whether record 1 can follow record 0: seq grows by a plausible step, cycle and time never
    go back. Operators only, so it takes Python ints (logs/plain.py) and NumPy arrays alike (the
    reader, under ``np.errstate(over="ignore")``: an unsigned step below zero wraps, and the first
    term is then false anyway)."""
    return (seq1 > seq0) & (seq1 - seq0 <= MAX_SEQ_JUMP) & (cyc1 >= cyc0) & (t1 >= t0)


def field_names(names: list[str], reserved: tuple[str, ...]) -> list[str]:
    """Unique column names: a variable called like a header field (the loop probe logs
    `cycle`) or like an earlier variable becomes `<name>_2`, `<name>_3`, ...; the logged
    name is kept in Variable.name."""
    taken = set(reserved)
    out = []
    for i, name in enumerate(names):
        base = name or f"var{i}"
        candidate, k = base, 2
        while candidate in taken:
            candidate, k = f"{base}_{k}", k + 1
        taken.add(candidate)
        out.append(candidate)
    return out


def logged_names(names: list[Any]) -> list[str]:
    """A name that is not valid Unicode text (a lone surrogate from a JSON ``\\udcff`` escape:
    whoever wrote the file chose it) is kept with that character written out (``\\udcff``), so
    every column name can be encoded: CSV, Parquet, rrd and the JSON listing never fail on it."""
    return [n.encode("utf-8", "backslashreplace").decode("utf-8") if isinstance(n, str) else str(n) for n in names]


def var_types(path: Path, names: list[str], codes: list[int]) -> list[VarType]:
    """Each variable's type; LogFormatError for a code rt_core does not define."""
    out = []
    for name, code in zip(names, codes):
        vt = VAR_TYPES.get(code)
        if vt is None:
            raise LogFormatError(
                f"{path}: variable {name!r} has unknown type code {code} "
                f"(known: {', '.join(f'{c} {t.name}' for c, t in VAR_TYPES.items())})"
            )
        out.append(vt)
    return out


@dataclass(frozen=True)
class SegmentLayout:
    """One segment's header, checked: where its records are and what is in them."""

    header: dict[str, Any]
    names: list[str]  # as logged (logged_names)
    fields: list[str]  # column names (field_names)
    types: list[VarType]
    offsets: list[int]  # of each variable, from the start of the payload
    stride: int  # bytes from one record to the next
    data: int  # file offset of the first record


def parse_segment_header(path: Path, buf: Any, size: int, pos: int) -> SegmentLayout:
    """The segment whose magic is at `pos` of `buf` (bytes-like, `size` long). Damaged: the header
    does not parse (skip it); LogFormatError: it parses, but not into something this reader knows."""
    if pos + PREFIX_SIZE > size:
        raise Damaged(f"segment header cut short ({size - pos} bytes)")
    (jlen,) = struct.unpack_from("<I", buf, pos + JSON_LEN_OFFSET)
    (stride,) = struct.unpack_from("<I", buf, pos + STRIDE_OFFSET)
    if jlen == 0 or jlen > MAX_HEADER_BYTES or pos + PREFIX_SIZE + jlen > size:
        raise Damaged(f"implausible JSON header length {jlen}")
    try:
        header = json.loads(bytes(buf[pos + PREFIX_SIZE : pos + PREFIX_SIZE + jlen]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise Damaged(f"JSON header does not parse ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != "xrflog":
        raise Damaged("header is not an xrflog header")
    # From here on the header is readable: what we do not understand is an error, not damage.
    if header.get("version") != FORMAT_VERSION:
        raise LogFormatError(
            f"{path}: segment at offset {pos} has xrflog version {header.get('version')!r}; "
            f"this reader knows version {FORMAT_VERSION}"
        )
    try:
        spec = header["variables"]
        names = [str(v["name"]) for v in spec]
        codes = [int(v["type"]) for v in spec]
        offsets = [int(v["offset"]) for v in spec]
        record_size = int(header["record_size"])
    except (KeyError, TypeError, ValueError) as exc:
        raise LogFormatError(f"{path}: segment at offset {pos}: header lacks variables/record_size ({exc})") from None
    names = logged_names(names)
    types = var_types(path, names, codes)
    end = max((off + vt.size for off, vt in zip(offsets, types)), default=0)
    if end > record_size or RECORD_HEADER_SIZE + record_size > stride:
        raise LogFormatError(
            f"{path}: segment at offset {pos}: variables need {end} bytes, record_size is "
            f"{record_size}, stride {stride}: inconsistent header"
        )
    data = pos + (PREFIX_SIZE + jlen + ALIGN - 1) // ALIGN * ALIGN  # counted from the segment's start
    return SegmentLayout(header, names, field_names(names, XRFLOG_RESERVED), types, offsets, stride, data)
