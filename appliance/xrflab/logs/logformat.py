"""The xrflog file format as rt_core defines it, seen from Python.

rt_core/include/xrf/logformat.h is the one definition of a segment header: the magic, the fixed
prefix's layout, the variable type codes with their names, and ``xrf_logfile_header``, which
composes a header. This module reads all of it through the cffi binding (``_cffi_build``) and adds
nothing of its own, so the host log writer (logs/host_writer.py, through logs/log_channel.py)
writes the bytes the loop's own writer (rt_core/src/logfile.cpp) writes, and the reader
(logs/reader.py) knows the types the writers know.
A second copy of any of it could silently disagree with the loop (issue 20).

Standard library and cffi only, no NumPy: the light conversion child (logs/plain.py) reads the
layout from here too, and a NumPy type is made only when the reader asks for one (``VarType.dtype``).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from typing import Any

from .. import _cffi_build

_binding = _cffi_build.load()
ffi = _binding.ffi
lib = _binding.lib

MAGIC: bytes = bytes(ffi.buffer(lib.xrf_logfile_magic, lib.XRF_LOGFILE_MAGIC_SIZE))
FORMAT_VERSION: int = lib.XRF_LOGFILE_VERSION
# The segment prefix: magic, J (JSON length) and S (stride) as uint32 LE, then the JSON, padded so
# the records start at a multiple of ALIGN from the segment's first byte.
JSON_LEN_OFFSET: int = lib.XRF_LOGFILE_JSON_LEN_OFFSET
STRIDE_OFFSET: int = lib.XRF_LOGFILE_STRIDE_OFFSET
PREFIX_SIZE: int = lib.XRF_LOGFILE_PREFIX_SIZE
ALIGN: int = lib.XRF_LOGFILE_ALIGN
HEADER_MAX: int = lib.XRF_LOGFILE_HEADER_MAX

# Every record starts with the ring slot's header (channels.h struct xrf_slot_hdr: seq, cycle,
# t_ns), written as it is in memory: its fields, offsets and size come from the struct itself.
_SLOT_HDR = ffi.typeof("struct xrf_slot_hdr")
RECORD_HEADER_SIZE: int = ffi.sizeof(_SLOT_HDR)
# (name, little-endian NumPy type, offset) per field
RECORD_HEADER: tuple[tuple[str, str, int], ...] = tuple(
    (name, f"<{'i' if field.type.cname.startswith('int') else 'u'}{ffi.sizeof(field.type)}", field.offset)
    for name, field in _SLOT_HDR.fields
)


@dataclass(frozen=True)
class VarType:
    code: int  # XRF_LOG_* (XRF2's code)
    name: str  # XRF2's C name: "int", "long int", ...
    header_dtype: str  # the segment header's "dtype": "int32", "int64", ...
    typestr: str  # the record field as a NumPy type string, "<f8" (char is one raw byte, "|S1": logformat.h says why)

    @property
    def dtype(self) -> Any:
        """The record field's NumPy dtype (NumPy imported here, not by the module)."""
        import numpy as np

        return np.dtype(self.typestr)

    @property
    def size(self) -> int:
        return int(self.typestr[2:])

    @property
    def struct_code(self) -> str:
        return struct_code(self.typestr)


# NumPy's type strings as `struct` format characters (little-endian, standard sizes). char and bool
# are their unsigned byte, as the converters write them (a bool byte of 2 stays 2).
_STRUCT_CODES = {"f4": "f", "f8": "d", "i4": "i", "i8": "q", "u8": "Q", "b1": "B", "S1": "B", "u1": "B"}


def struct_code(typestr: str) -> str:
    """`struct`'s character for a field of NumPy type string `typestr` ("<f8" -> "d"). KeyError
    for a type this table lacks (a type rt_core gains later: the NumPy reader still reads it)."""
    code = _STRUCT_CODES[typestr[1:]]
    if struct.calcsize("<" + code) != int(typestr[2:]):
        raise KeyError(typestr)
    return code


def _text(p: Any) -> str:
    return ffi.string(p).decode("ascii")


VAR_TYPES: dict[int, VarType] = {
    int(t.code): VarType(int(t.code), _text(t.name), _text(t.dtype), _text(t.typestr)) for t in lib.xrf_logfile_types
}


def _c_text(value: str | bytes) -> Any:
    raw = value if isinstance(value, bytes) else value.encode("utf-8", "replace")
    return ffi.new("char[]", raw)


def segment_header(
    meta: Any,
    stride: int,
    *,
    program: str | bytes,
    pid: int,
    cycle_freq: int,
    start_unix_ns: int,
    start_mono_ns: int,
    project: str | bytes = "",
    build: str | bytes = "",
    run: str | bytes = "",
) -> bytes:
    """A segment header by rt_core's ``xrf_logfile_header``. `meta`: a ``struct xrf_log_meta``
    (the run's shared memory's, or one a test fills in), as cdata or a pointer to it. Texts given
    as bytes reach C unchanged (the loop's program name as it sits in the shared memory).
    Raises OSError with C's errno (ENAMETOOLONG: a text longer than XRF_LOGFILE_TEXT_MAX)."""
    if ffi.typeof(meta).kind == "struct":
        meta = ffi.addressof(meta)
    texts = {k: _c_text(v) for k, v in (("program", program), ("project", project), ("build", build), ("run", run))}
    ident = ffi.new(
        "struct xrf_logfile_ident *",
        {
            **texts,
            "pid": pid,
            "cycle_freq": cycle_freq,
            "start_unix_ns": start_unix_ns,
            "start_mono_ns": start_mono_ns,
        },
    )
    buf = ffi.new("char[]", HEADER_MAX)
    n = lib.xrf_logfile_header(buf, HEADER_MAX, ident, meta, stride)
    if n < 0:
        raise OSError(-n, f"cannot compose the log segment header: {os.strerror(-n)}")
    return bytes(ffi.buffer(buf, n))


__all__ = [
    "ALIGN",
    "FORMAT_VERSION",
    "HEADER_MAX",
    "JSON_LEN_OFFSET",
    "MAGIC",
    "PREFIX_SIZE",
    "STRIDE_OFFSET",
    "VAR_TYPES",
    "VarType",
    "segment_header",
]
