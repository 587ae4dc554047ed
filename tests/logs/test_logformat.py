"""The segment header has one definition, rt_core's logformat.h (issue 20): the reader decodes what
its C composer writes for every type code, Python's type table is C's, awkward names and texts
still make a header that parses, the size bound holds, and no copy of the magic or of a type
table exists anywhere else in the repository."""

from __future__ import annotations

import errno
import json
import re
import struct
from pathlib import Path

import pytest

from xrf_testing.writers import TYPES
from xrflab.logs import LogFormatError, logformat, open_log
from xrflab.logs.logformat import MAGIC, VAR_TYPES, ffi, lib

REPO = Path(__file__).resolve().parents[2]
IDENT = {
    "program": "probe",
    "pid": 4321,
    "cycle_freq": 1000,
    "start_unix_ns": 1_795_000_000_123_456_789,
    "start_mono_ns": 98_765_432_101,
    "project": "p",
    "build": "b",
    "run": "12",
}


def _meta(variables: list[tuple[bytes, int]]):
    """A struct xrf_log_meta as a loop publishes it: packed offsets, record_size their sum."""
    m = ffi.new("struct xrf_log_meta *")
    pos = 0
    for i, (name, code) in enumerate(variables):
        ffi.memmove(m.vars[i].name, name, len(name))
        m.vars[i].type = code
        m.vars[i].offset = pos
        pos += TYPES[code][1] if code in TYPES else 1
    m.nvars = len(variables)
    m.record_size = pos
    return m


def _stride(record_size: int) -> int:
    return (24 + record_size + 7) // 8 * 8


def _json(header: bytes) -> dict:
    jlen = struct.unpack_from("<I", header, lib.XRF_LOGFILE_JSON_LEN_OFFSET)[0]
    return json.loads(header[lib.XRF_LOGFILE_PREFIX_SIZE : lib.XRF_LOGFILE_PREFIX_SIZE + jlen])


def test_python_type_table_is_the_c_table() -> None:
    codes = list(range(1, lib.XRF_LOG_NTYPES + 1))
    assert sorted(VAR_TYPES) == codes
    for code in codes:
        c = lib.xrf_logfile_type_of(code)
        vt = VAR_TYPES[code]
        assert (vt.code, vt.name, vt.header_dtype) == (
            c.code,
            ffi.string(c.name).decode(),
            ffi.string(c.dtype).decode(),
        )
        assert vt.dtype.itemsize == c.size == TYPES[code][1]  # and the spec-written fixture writer agrees
    for code in (0, -1, lib.XRF_LOG_NTYPES + 1, 255):
        assert lib.xrf_logfile_type_of(code) == ffi.NULL
    # The spec's sentence naming the codes (file-format.md) says what C says.
    spec = (REPO / "docs/logging/file-format.md").read_text()
    listed = re.search(r"`type` is XRF2's code \(([^)]*)\)", spec)
    assert listed is not None
    assert listed.group(1) == ", ".join(f"{c} {VAR_TYPES[c].name}" for c in codes)
    assert MAGIC == bytes.fromhex("5852464C4F47310A") and len(MAGIC) == lib.XRF_LOGFILE_MAGIC_SIZE


@pytest.mark.parametrize("code", sorted(VAR_TYPES))
def test_reader_decodes_a_c_header_of_every_type(tmp_path: Path, code: int) -> None:
    variables = [(b"before", 5), (b"x", code), (b"after", 3)]
    m = _meta(variables)
    stride = _stride(m.record_size)
    header = logformat.segment_header(m, stride, **IDENT)
    assert header[:8] == MAGIC and len(header) % lib.XRF_LOGFILE_ALIGN == 0
    assert struct.unpack_from("<I", header, lib.XRF_LOGFILE_STRIDE_OFFSET)[0] == stride
    values = {
        1: [True, False, True],
        2: [b"a", b"\xff", b"z"],
        3: [-(2**31), 7, 2**31 - 1],
        4: [1.5, -0.25, float("inf")],
        5: [0.1, -1e300, 2.0],
        6: [-(2**63), 5, 2**63 - 1],
    }[code]
    fmt = "<d" + TYPES[code][0] + "i"
    body = b"".join(
        struct.pack("<QQq", i, 100 + i, 10_000 + i)
        + struct.pack(fmt, 0.5 * i, v, i)
        + b"\0" * (stride - 24 - struct.calcsize(fmt))
        for i, v in enumerate(values)
    )
    path = tmp_path / "c.xrf"
    path.write_bytes(header + body)
    log = open_log(path)
    assert log.skipped == [] and len(log) == 3
    seg = log.segments[0]
    assert [(v.name, v.code, v.type_name, v.dtype) for v in seg.variables] == [
        ("before", 5, "double", VAR_TYPES[5].dtype),
        ("x", code, VAR_TYPES[code].name, VAR_TYPES[code].dtype),
        ("after", 3, "int", VAR_TYPES[3].dtype),
    ]
    assert list(seg.records["x"]) == values
    assert list(seg.records["after"]) == [0, 1, 2]
    h = seg.header
    assert h["variables"][1] == {"name": "x", "type": code, "dtype": VAR_TYPES[code].header_dtype, "offset": 8}
    assert {k: h[k] for k in IDENT} == IDENT
    assert h["version"] == lib.XRF_LOGFILE_VERSION and h["record_size"] == m.record_size


def test_awkward_names_and_texts_still_make_a_header_that_parses(tmp_path: Path) -> None:
    full = b"n" * lib.XRF_NAME_MAX  # no NUL: the name fills its field
    names = [b'q"uo\\te', b"tab\there\n", "für_π".encode(), b"bad\xff\xc3(", full]
    m = _meta([(n, 5) for n in names])
    ident = dict(IDENT, program=b"prog\x01", project='pro"ject\\', run="ünï")
    header = logformat.segment_header(m, _stride(m.record_size), **ident)
    h = _json(header)
    assert [v["name"] for v in h["variables"]] == [
        'q"uo\\te',
        "tab\there\n",
        "für_π",
        "bad\ufffd\ufffd(",
        "n" * lib.XRF_NAME_MAX,
    ]
    assert (h["program"], h["project"], h["run"]) == ("prog\x01", 'pro"ject\\', "ünï")
    # Control characters as \u00XX (the bytes the loop wrote before there was one composer).
    assert b'"tab\\u0009here\\u000a"' in header and b'"prog\\u0001"' in header
    path = tmp_path / "awkward.xrf"
    path.write_bytes(header)
    assert [v.field for v in open_log(path).variables][:2] == ['q"uo\\te', "tab\there\n"]


def test_the_largest_header_fits_the_bound_and_longer_texts_are_refused() -> None:
    m = _meta([(bytes([1 + i % 30]) * lib.XRF_NAME_MAX, 6) for i in range(lib.XRF_LOG_VARS_MAX)])
    worst = "\x1f" * lib.XRF_LOGFILE_TEXT_MAX
    ident = dict(
        IDENT,
        program=worst,
        project=worst,
        build=worst,
        run=worst,
        pid=-(2**31),
        start_unix_ns=-(2**63),
        start_mono_ns=-(2**63),
    )
    header = logformat.segment_header(m, 2**32 - 1, **ident)
    assert len(header) <= lib.XRF_LOGFILE_HEADER_MAX
    assert len(_json(header)["variables"]) == lib.XRF_LOG_VARS_MAX
    with pytest.raises(OSError) as too_long:
        logformat.segment_header(m, 8, **dict(IDENT, build="b" * (lib.XRF_LOGFILE_TEXT_MAX + 1)))
    assert too_long.value.errno == errno.ENAMETOOLONG
    small = ffi.new("char[]", len(header) - 1)
    keep = [ffi.new("char[]", worst.encode()) for _ in range(4)]
    cid = ffi.new(
        "struct xrf_logfile_ident *",
        {
            "program": keep[0],
            "project": keep[1],
            "build": keep[2],
            "run": keep[3],
            "pid": -(2**31),
            "cycle_freq": 1000,
            "start_unix_ns": -(2**63),
            "start_mono_ns": -(2**63),
        },
    )
    assert lib.xrf_logfile_header(small, len(small), cid, m, 2**32 - 1) == -errno.ENOSPC
    assert lib.xrf_logfile_header(ffi.NULL, 0, cid, m, 8) == -errno.EINVAL


def test_an_unknown_type_code_is_written_as_such_and_refused_by_name(tmp_path: Path) -> None:
    m = _meta([(b"odd", 9)])
    header = logformat.segment_header(m, _stride(m.record_size), **IDENT)
    assert _json(header)["variables"][0]["dtype"] == "?"
    path = tmp_path / "odd.xrf"
    path.write_bytes(header)
    with pytest.raises(LogFormatError, match=r"'odd' has unknown type code 9"):
        open_log(path)


# A type table: a type code mapped to one of the names of C's table (as a dict entry, a tuple, a
# C case/initialiser). Matched in every source file but the format's home.
HOME = {"rt_core/include/xrf/logformat.h", "rt_core/src/logformat.c"}
_NAMES = "|".join(re.escape(n) for t in VAR_TYPES.values() for n in {t.name, t.header_dtype})
_TABLE = re.compile(
    r"(\b[1-6]\s*[:,]\s*(VarType\(\s*[1-6]\s*,\s*)?[\"'](" + _NAMES + r")[\"'])"
    r"|(XRF_LOG_[A-Z_]+\s*:\s*return\s*\"(" + _NAMES + r")\")"
)


def _sources() -> list[Path]:
    roots = ["appliance", "bench", "tests", "rt_core", "frontend", "deploy", "student_projects"]
    out = []
    for root in roots:
        for path in (REPO / root).rglob("*"):
            parts = path.relative_to(REPO).parts
            if (
                path.suffix in (".py", ".c", ".cpp", ".h", ".hpp", ".js", ".sh")
                and path.is_file()
                and not any(p == "build" or p.startswith(".") for p in parts)
            ):
                out.append(path)
    return out


def test_no_copy_of_the_magic_or_a_type_table_exists() -> None:
    needle = MAGIC[:-1]  # "XRFLOG1" without writing it here
    own = Path(__file__).resolve()
    magic_copies, tables = [], []
    for path in _sources():
        if path.resolve() == own:
            continue
        data = path.read_bytes()
        rel = str(path.relative_to(REPO))
        if rel in HOME:
            continue
        if needle in data:
            magic_copies.append(rel)
        tables += [f"{rel}: {m.group(0)}" for m in _TABLE.finditer(data.decode("utf-8", "replace"))]
    assert magic_copies == [], "the magic must come from logformat.h (logs/logformat.py in Python)"
    assert tables == [], "type names must come from logformat.h's xrf_logfile_types"
    # The check itself finds what it is for.
    assert _TABLE.search('TYPE_NAMES = {1: "bool", 3: "int32"}') and _TABLE.search('3: VarType(3, "int", x)')
    assert _TABLE.search('case XRF_LOG_INT: return "int32";')
