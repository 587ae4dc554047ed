"""XRF2's `.bin` log files: names line, type-codes line, then packed little-endian records.

XRF2 wrote `name1,name2,...\n`, `5,5,3,...\n` and then copies of the `#pragma pack(1)`
struct, nothing else: no sequence numbers or timestamps, so the decoded records get a
synthesized index (`seq` = 0, 1, 2, ...) and no cycle/t_ns columns. The stride is the sum of
the type sizes. XRF2's own decoder used NumPy aliases removed in NumPy 2 (`np.float`,
`np.int`, `np.bool`); this one uses explicit little-endian dtypes only.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from .reader import LogFile, LogFormatError, Segment, make_variables, record_dtype, register_format

# Both header lines fit in this many bytes (100 variables of 31-character names is ~3.2 KB).
MAX_HEADER_SCAN = 64 * 1024
_CODES_LINE = re.compile(rb"^[0-9 ,\r]*$")


def _split(line: bytes) -> list[str]:
    items = [s.strip() for s in line.decode("utf-8", "replace").rstrip("\r").split(",")]
    # XRF2 variants end the line with a separator: a trailing empty item is not a variable.
    if items and items[-1] == "":
        items.pop()
    return items


def try_read(path: Path, buf: Any, size: int) -> LogFile | None:
    """Decode `buf` as an XRF2 file, or None when it does not start like one. A file whose
    header looks like XRF2's but names an unknown type code raises LogFormatError."""
    head = bytes(buf[: min(size, MAX_HEADER_SCAN)])
    first = head.find(b"\n")
    second = head.find(b"\n", first + 1) if first >= 0 else -1
    if first <= 0 or second < 0:
        return None
    names_line, codes_line = head[:first], head[first + 1 : second]
    if not _CODES_LINE.match(codes_line) or b"\0" in names_line:
        return None
    names, code_text = _split(names_line), _split(codes_line)
    if not names or not code_text or not all(c.isdigit() for c in code_text):
        return None
    if len(names) != len(code_text):
        raise LogFormatError(f"{path}: XRF2 header names {len(names)} variables but gives {len(code_text)} type codes")
    variables = make_variables(path, names, [int(c) for c in code_text], None, ("seq",))
    stride = sum(v.dtype.itemsize for v in variables)
    data = second + 1
    n = (size - data) // stride
    dtype = record_dtype(variables, stride, header=False)
    records = np.ndarray((n,), dtype=dtype, buffer=buf, offset=data) if n else np.empty(0, dtype=dtype)
    header = {
        "format": "xrf2",
        "variables": [{"name": v.name, "type": v.code, "offset": v.offset} for v in variables],
        "record_size": stride,
    }
    log = LogFile(path, "xrf2", size=size)
    log.segments.append(Segment(0, 0, header, variables, records, kind="xrf2"))
    rest = size - data - n * stride
    if rest:
        log.note_skipped(f"offset {data + n * stride}: truncated last record, {rest} bytes skipped", rest)
    return log


register_format(try_read)  # open_log tries it on a file without the xrflog magic
