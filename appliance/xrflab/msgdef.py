#!/usr/bin/env python3
"""ROS ``.msg`` files -> packed C++ structs for the loop, and a Python codec for the host side.

A student project's ``msg/Ros2Xeno.msg`` and ``msg/Xeno2Ros.msg`` are the single source of the
messages between host and loop. This module parses the subset of the .msg syntax that a
fixed-size, packed, real-time-safe struct can carry (scalars and fixed arrays), generates
``xrf2_msgs/msg/ros2_xeno.hpp`` and ``xrf2_msgs/msg/xeno2_ros.hpp`` (the headers XRF2 code
includes), and encodes/decodes the same bytes in Python with ``struct``.

Standard library only: CMake runs this file as a script at configure time, before any venv.

    python3 msgdef.py --msg-dir PROJECT/msg --out BUILD/generated
"""

from __future__ import annotations

import argparse
import re
import struct
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# Must equal XRF_MSG_MAX in rt_core/include/xrf/channels.h (a test checks it): this module is
# stdlib-only and runs before the binding exists, so it cannot read the value from cffi.
MSG_MAX_BYTES = 512

# The two messages of a project: .msg name -> (struct name, header path under the output dir).
PROJECT_MESSAGES = ("Ros2Xeno", "Xeno2Ros")


@dataclass(frozen=True)
class PrimitiveType:
    struct_code: str  # struct module format character (little-endian, packed)
    cpp: str
    python: type


PRIMITIVES: dict[str, PrimitiveType] = {
    "bool": PrimitiveType("?", "bool", bool),
    "byte": PrimitiveType("B", "uint8_t", int),
    # ROS 2 maps char to an unsigned 8-bit integer; doing the same keeps decoded values numbers.
    "char": PrimitiveType("B", "uint8_t", int),
    "int8": PrimitiveType("b", "int8_t", int),
    "uint8": PrimitiveType("B", "uint8_t", int),
    "int16": PrimitiveType("h", "int16_t", int),
    "uint16": PrimitiveType("H", "uint16_t", int),
    "int32": PrimitiveType("i", "int32_t", int),
    "uint32": PrimitiveType("I", "uint32_t", int),
    "int64": PrimitiveType("q", "int64_t", int),
    "uint64": PrimitiveType("Q", "uint64_t", int),
    "float32": PrimitiveType("f", "float", float),
    "float64": PrimitiveType("d", "double", float),
}
SUPPORTED = ", ".join(PRIMITIVES)

# ROS 2 field-name rule: lower case, starts with a letter, no double or trailing underscore.
_NAME_RE = re.compile(r"^[a-z][a-z0-9]*(_[a-z0-9]+)*$")
_TYPE_RE = re.compile(r"^(?P<base>[A-Za-z_][A-Za-z0-9_/]*)(?P<array>\[(?P<bound><=)?(?P<size>[0-9]*)\])?$")
# Names a generated C++ struct cannot use as members.
_CPP_KEYWORDS = frozenset(
    """alignas alignof and and_eq asm auto bitand bitor bool break case catch char char16_t
    char32_t class compl const constexpr const_cast continue decltype default delete do double
    dynamic_cast else enum explicit export extern false float for friend goto if inline int long
    mutable namespace new noexcept not not_eq nullptr operator or or_eq private protected public
    register reinterpret_cast return short signed sizeof static static_assert static_cast struct
    switch template this thread_local throw true try typedef typeid typename union unsigned using
    virtual void volatile wchar_t while xor xor_eq""".split()
)


class MsgError(Exception):
    """A .msg file this toolchain cannot turn into a packed struct; str() is ``path:line: why``."""

    def __init__(self, path: str | Path, line: int, message: str) -> None:
        self.path = str(path)
        self.line = line
        self.message = message
        super().__init__(f"{self.path}:{line}: {message}" if line else f"{self.path}: {message}")


@dataclass(frozen=True)
class Field:
    type: str  # the .msg primitive name
    name: str
    count: int | None = None  # fixed array length, None for a scalar

    @property
    def primitive(self) -> PrimitiveType:
        return PRIMITIVES[self.type]

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.primitive.struct_code) * (self.count or 1)

    def schema_line(self) -> str:
        return f"{self.type}[{self.count}] {self.name}" if self.count else f"{self.type} {self.name}"


# ---- parsing ------------------------------------------------------------------------------------


def _parse_field(text: str, path: str, lineno: int) -> Field:
    if "=" in text.replace("<=", ""):  # `<=` is a bound (type[<=N], string<=N), not a constant
        raise MsgError(path, lineno, f"constants are not supported: {text!r}")
    tokens = text.split()
    if len(tokens) == 1:
        raise MsgError(path, lineno, f"expected 'type name', got {text!r}")
    if len(tokens) > 2:
        raise MsgError(path, lineno, f"default values are not supported: {text!r}")
    type_text, name = tokens
    match = _TYPE_RE.match(type_text)
    if match is None:
        raise MsgError(path, lineno, f"cannot read type {type_text!r}")
    base = match["base"]
    if base not in PRIMITIVES:
        if "/" in base or base[0].isupper():
            raise MsgError(path, lineno, f"nested message type '{base}' is not supported (supported: {SUPPORTED})")
        raise MsgError(path, lineno, f"unsupported type '{base}' (supported: {SUPPORTED})")
    count: int | None = None
    if match["array"]:
        if match["bound"] or not match["size"]:
            raise MsgError(
                path, lineno, f"'{type_text}': only fixed-size arrays type[N] are supported (the struct is fixed-size)"
            )
        count = int(match["size"])
        if count < 1:
            raise MsgError(path, lineno, f"'{type_text}': array length must be at least 1")
    if not _NAME_RE.match(name):
        raise MsgError(
            path,
            lineno,
            f"bad field name '{name}' (lower case letters, digits and single underscores, starting with a letter)",
        )
    if name in _CPP_KEYWORDS:
        raise MsgError(path, lineno, f"field name '{name}' is a C++ keyword")
    return Field(base, name, count)


def parse_msg_text(text: str, path: str | Path = "<msg>") -> list[Field]:
    """Fields of one .msg text, in order. Raises MsgError naming path and line."""
    path = str(path)
    fields: list[Field] = []
    first_line: dict[str, int] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        f = _parse_field(line, path, lineno)
        if f.name in first_line:
            raise MsgError(path, lineno, f"duplicate field '{f.name}' (first on line {first_line[f.name]})")
        first_line[f.name] = lineno
        fields.append(f)
    size = sum(f.size for f in fields)
    if size > MSG_MAX_BYTES:
        raise MsgError(path, 0, f"message is {size} bytes; the channel carries at most {MSG_MAX_BYTES}")
    return fields


def parse_msg_file(path: str | Path) -> list[Field]:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MsgError(path, 0, "file not found") from None
    except UnicodeDecodeError as exc:
        raise MsgError(path, 0, f"not UTF-8 text ({exc.reason})") from None
    return parse_msg_text(text, path)


def schema_text(fields: Iterable[Field]) -> str:
    """The normalised schema stored in shared memory: one ``type name`` per line."""
    return "\n".join(f.schema_line() for f in fields)


def parse_schema(text: str) -> list[Field]:
    return parse_msg_text(text, "<schema>")


# ---- the Python codec ---------------------------------------------------------------------------


class Codec:
    """Packs and unpacks one message exactly as the generated ``#pragma pack(1)`` struct lays it out."""

    def __init__(self, schema: str | Iterable[Field]) -> None:
        self.fields: list[Field] = parse_schema(schema) if isinstance(schema, str) else list(schema)
        self._by_name = {f.name: f for f in self.fields}
        self._struct = struct.Struct("<" + "".join(f"{f.count or ''}{f.primitive.struct_code}" for f in self.fields))
        self.size: int = self._struct.size
        self.schema: str = schema_text(self.fields)

    @property
    def field_names(self) -> list[str]:
        return [f.name for f in self.fields]

    def offsets(self) -> dict[str, int]:
        offsets, at = {}, 0
        for f in self.fields:
            offsets[f.name] = at
            at += f.size
        return offsets

    def _unknown(self, names: Iterable[str]) -> None:
        unknown = sorted(set(names) - set(self._by_name))
        if unknown:
            valid = ", ".join(self.field_names) or "(none: the message is empty)"
            raise ValueError(f"unknown field(s) {', '.join(unknown)}; valid fields: {valid}")

    def encode(self, values: dict[str, Any] | None = None) -> bytes:
        """Bytes of the struct; fields not given are 0/False, unknown ones raise ValueError."""
        values = values or {}
        self._unknown(values)
        flat: list[Any] = []
        for f in self.fields:
            v = values.get(f.name)
            if f.count is None:
                flat.append(f.primitive.python(0) if v is None else v)
                continue
            items = [f.primitive.python(0)] * f.count if v is None else list(v)
            if len(items) != f.count:
                raise ValueError(f"field {f.name}: expected {f.count} values, got {len(items)}")
            flat.extend(items)
        try:
            return self._struct.pack(*flat)
        except struct.error as exc:
            raise ValueError(f"cannot encode {values!r} as {self.schema!r}: {exc}") from None

    def decode(self, data: bytes) -> dict[str, Any]:
        """Field values from the first `size` bytes of data (the loop may pad its copy)."""
        if len(data) < self.size:
            raise ValueError(f"need {self.size} bytes, got {len(data)}")
        flat = self._struct.unpack_from(data)
        out: dict[str, Any] = {}
        at = 0
        for f in self.fields:
            if f.count is None:
                out[f.name] = flat[at]
                at += 1
            else:
                out[f.name] = list(flat[at : at + f.count])
                at += f.count
        return out

    def parse_value(self, name: str, text: str) -> Any:
        """A field value from command-line text: ``1.5``, ``true``, ``0x10``, ``1,2,3``."""
        self._unknown([name])
        f = self._by_name[name]
        if f.count is None:
            return _parse_scalar(f, text)
        parts = [p for p in text.strip().strip("[]").split(",") if p.strip()]
        return [_parse_scalar(f, p) for p in parts]


def _parse_scalar(f: Field, text: str) -> Any:
    text = text.strip()
    try:
        if f.primitive.python is bool:
            lowered = text.lower()
            if lowered in ("1", "true", "yes", "on"):
                return True
            if lowered in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if f.primitive.python is int:
            return int(text, 0)
        return float(text)
    except ValueError:
        raise ValueError(f"field {f.name} ({f.type}): cannot read {text!r}") from None


# ---- C++ generation -----------------------------------------------------------------------------


def snake_case(name: str) -> str:
    """ROS's header naming: Ros2Xeno -> ros2_xeno, Xeno2Ros -> xeno2_ros, HTTPServer -> http_server."""
    # An underscore before a capital that follows a lower-case letter or digit ...
    out = re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", name)
    # ... and before the last capital of a run of capitals that starts a new word.
    out = re.sub(r"(?<=[A-Z])([A-Z][a-z])", r"_\1", out)
    return out.lower()


def header_relpath(message: str) -> Path:
    return Path("xrf2_msgs") / "msg" / f"{snake_case(message)}.hpp"


def _cpp_member(f: Field) -> str:
    cpp = f.primitive.cpp
    if f.count is None:
        return f"    {cpp} {f.name} = {'false' if cpp == 'bool' else '0'};"
    return f"    std::array<{cpp}, {f.count}> {f.name}{{}};"


def generate_header(message: str, fields: list[Field], source: str = "") -> str:
    schema = schema_text(fields).replace("\n", "\\n")
    guard = f"XRF2_MSGS__MSG__{snake_case(message).upper()}_HPP"
    size = sum(f.size for f in fields)
    members = "\n".join(_cpp_member(f) for f in fields)
    layout_check = (
        f'static_assert(sizeof({message}) == {size}, "{message}: layout differs from the Python codec");\n'
        if fields  # an empty C++ struct still takes one byte
        else ""
    )
    origin = f" from {source}" if source else ""
    return f"""// Generated by xrflab/msgdef.py{origin}. Do not edit: change the .msg file instead.
#ifndef {guard}
#define {guard}

#include <array>
#include <cstdint>
#include <type_traits>

namespace xrf2_msgs {{
namespace msg {{

// Packed, so that the Python codec (struct, '<' format) reads the same bytes the loop writes.
#pragma pack(push, 1)
struct {message} {{
{members}
    static constexpr const char *XRF_SCHEMA = "{schema}";
}};
#pragma pack(pop)

static_assert(sizeof({message}) <= {MSG_MAX_BYTES},
              "{message} is larger than the {MSG_MAX_BYTES} bytes a host/loop channel carries (XRF_MSG_MAX)");
{layout_check}static_assert(std::is_trivially_copyable<{message}>::value, "{message} is copied as raw bytes");

}}  // namespace msg
}}  // namespace xrf2_msgs

#endif  // {guard}
"""


def _write_if_changed(path: Path, text: str) -> None:
    # Rewriting an unchanged header would make every build recompile the controller.
    if path.exists() and path.read_text() == text:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def generate_project_headers(msg_dir: str | Path, out_dir: str | Path) -> list[Path]:
    """Parse the project's two .msg files and write their headers; returns the header paths."""
    msg_dir, out_dir = Path(msg_dir), Path(out_dir)
    if not msg_dir.is_dir():
        raise MsgError(msg_dir, 0, "message folder not found (a project keeps Ros2Xeno.msg and Xeno2Ros.msg in msg/)")
    parsed = {}
    for message in PROJECT_MESSAGES:
        path = msg_dir / f"{message}.msg"
        if not path.is_file():
            raise MsgError(path, 0, f"missing: a project needs {' and '.join(m + '.msg' for m in PROJECT_MESSAGES)}")
        parsed[message] = (path, parse_msg_file(path))
    written = []
    for message, (path, fields) in parsed.items():
        target = out_dir / header_relpath(message)
        _write_if_changed(target, generate_header(message, fields, source=path.name))
        written.append(target)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Generate the xrf2_msgs C++ headers from a project's .msg files.")
    parser.add_argument("--msg-dir", required=True, help="folder with Ros2Xeno.msg and Xeno2Ros.msg")
    parser.add_argument("--out", required=True, help="include folder to write xrf2_msgs/msg/*.hpp into")
    args = parser.parse_args(argv)
    try:
        for header in generate_project_headers(args.msg_dir, args.out):
            print(header)
    except MsgError as exc:
        print(exc, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
