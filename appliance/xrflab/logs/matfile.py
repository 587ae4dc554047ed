"""A MAT-file (level 5, uncompressed) writer in the standard library only, a variable at a time and
a column streamed in pieces, so a log of any length is written in bounded memory (logs/plain.py).

What it writes is what ``scipy.io.savemat(f, ..., format="5", oned_as="column",
long_field_names=True, do_compression=False)`` writes for the same values on a little-endian
machine, byte for byte after the 128-byte file header (whose text holds the time of writing):
tests/logs/test_plain_convert.py compares the two. The format's facts are MathWorks' "MAT-File
Format" (Level 5): a 128-byte header (116 bytes of text, an 8-byte subsystem offset, version
0x0100, the endian indicator "IM"), then one data element per variable, each a tag (type, byte
count) and its data padded to 8 bytes, or, for 4 bytes or fewer, a small element (type and count
in one 4-byte word, then the data in 4). A variable is a miMATRIX element holding its array flags
(class, logical), its dimensions, its name and its data. Little-endian always: the Pi and x86 are.

The choices that make it scipy's too: a column of n values is n x 1, and 0 x 0 when empty; text is
a 1 x n char array of UTF-8 (n characters; NULs become spaces, all-NUL or empty text is 0 x 0); a
bool column is uint8 with the logical flag; a struct's field name length is its longest name + 1;
nested arrays have an empty name.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import BinaryIO

MI_INT8, MI_UINT8, MI_INT32, MI_UINT32, MI_SINGLE, MI_DOUBLE = 1, 2, 5, 6, 7, 9
MI_INT64, MI_UINT64, MI_MATRIX, MI_UTF8 = 12, 13, 14, 16
MX_CELL, MX_STRUCT, MX_CHAR, MX_DOUBLE, MX_SINGLE = 1, 2, 4, 6, 7
MX_UINT8, MX_INT32, MX_INT64, MX_UINT64 = 9, 12, 14, 15
LOGICAL = 2 << 8  # array flags: the logical bit, above the class byte


@dataclass(frozen=True)
class NumClass:
    """How a column of one NumPy type string's values is stored: element type, class, flags."""

    mi: int
    mx: int
    size: int
    flags: int = 0


# NumPy type string (without the byte order) -> its MAT storage; "b1" and "S1" are bytes.
NUM_CLASSES = {
    "f8": NumClass(MI_DOUBLE, MX_DOUBLE, 8),
    "f4": NumClass(MI_SINGLE, MX_SINGLE, 4),
    "i4": NumClass(MI_INT32, MX_INT32, 4),
    "i8": NumClass(MI_INT64, MX_INT64, 8),
    "u8": NumClass(MI_UINT64, MX_UINT64, 8),
    "u1": NumClass(MI_UINT8, MX_UINT8, 1),
    "S1": NumClass(MI_UINT8, MX_UINT8, 1),
    "b1": NumClass(MI_UINT8, MX_UINT8, 1, LOGICAL),
}


def _pad8(n: int) -> int:
    return -n % 8


def element(mi: int, data: bytes) -> bytes:
    """One data element: a small element for 4 bytes or fewer, else tag, data, padding."""
    if len(data) <= 4:
        return struct.pack("<I", (len(data) << 16) | mi) + data.ljust(4, b"\0")
    return struct.pack("<II", mi, len(data)) + data + b"\0" * _pad8(len(data))


def element_size(nbytes: int) -> int:
    return 8 if nbytes <= 4 else 8 + nbytes + _pad8(nbytes)


def _matrix_head(mx: int, flags: int, dims: tuple[int, ...], name: str) -> bytes:
    """Array flags, dimensions and name of a miMATRIX element (its tag not included)."""
    out = struct.pack("<IIII", MI_UINT32, 8, mx | flags, 0)
    out += element(MI_INT32, struct.pack(f"<{len(dims)}i", *dims))
    return out + element(MI_INT8, name.encode("latin-1"))


def _matrix(mx: int, flags: int, dims: tuple[int, ...], name: str, body: bytes) -> bytes:
    content = _matrix_head(mx, flags, dims, name) + body
    return struct.pack("<II", MI_MATRIX, len(content)) + content


def column_dims(n: int) -> tuple[int, int]:
    """A column of n values: n x 1; none: 0 x 0 (as MATLAB's [])."""
    return (n, 1) if n else (0, 0)


def char_matrix(text: str, name: str = "") -> bytes:
    """`text` as a 1 x n char array of UTF-8 (UnicodeEncodeError for a lone surrogate)."""
    if text.strip("\0") == "":
        return _matrix(MX_CHAR, 0, (0, 0), name, element(MI_UTF8, b""))
    text = text.replace("\0", " ")
    return _matrix(MX_CHAR, 0, (1, len(text)), name, element(MI_UTF8, text.encode("utf-8")))


def numeric_matrix(typestr: str, dims: tuple[int, ...], data: bytes, name: str = "") -> bytes:
    """A numeric array of little-endian `data` (values in column order)."""
    c = NUM_CLASSES[typestr[1:]]
    return _matrix(c.mx, c.flags, dims, name, element(c.mi, data))


def cell_column(texts: list[str], name: str = "") -> bytes:
    """A len(texts) x 1 cell array of char arrays."""
    body = b"".join(char_matrix(t) for t in texts)
    return _matrix(MX_CELL, 0, (len(texts), 1), name, body)


def struct_matrix(fields: list[tuple[str, bytes]], name: str = "") -> bytes:
    """A 1 x 1 struct of the given (field name, nested matrix element) pairs, in order."""
    length = max(len(f) for f, _ in fields) + 1
    if length > 64:
        raise ValueError("Field names are restricted to 63 characters")
    names = b"".join(f.encode("latin-1").ljust(length, b"\0") for f, _ in fields)
    body = element(MI_INT32, struct.pack("<i", length)) + element(MI_INT8, names)
    return _matrix(MX_STRUCT, 0, (1, 1), name, body + b"".join(m for _, m in fields))


class MatWriter:
    """Writes a MAT file's header at once, then whole variables (``write``) or columns streamed in
    pieces (``write_column``)."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        text = f"MATLAB 5.0 MAT-file Platform: posix, Created on: {time.asctime()}".encode("ascii")
        f.write(text[:116].ljust(116, b"\0") + b"\0" * 8 + struct.pack("<H", 0x0100) + b"IM")

    def write(self, matrix: bytes) -> None:
        self.f.write(matrix)

    def write_column(self, name: str, typestr: str, n: int, pieces: Iterable[bytes]) -> None:
        """A column of `n` values of type `typestr` ("<f8"), its little-endian bytes given in
        pieces (n * size bytes in all: ValueError otherwise, after they were written)."""
        c = NUM_CLASSES[typestr[1:]]
        nbytes = n * c.size
        head = _matrix_head(c.mx, c.flags, column_dims(n), name)
        self.f.write(struct.pack("<II", MI_MATRIX, len(head) + element_size(nbytes)) + head)
        if nbytes <= 4:
            self.f.write(element(c.mi, b"".join(pieces)))
            return
        self.f.write(struct.pack("<II", c.mi, nbytes))
        written = 0
        for piece in pieces:
            self.f.write(piece)
            written += len(piece)
        if written != nbytes:
            raise ValueError(f"column {name}: {written} bytes written, {nbytes} announced")
        self.f.write(b"\0" * _pad8(nbytes))
