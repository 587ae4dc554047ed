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

# std_msgs/Header's frame_id (and TransformStamped's child_frame_id) in the loop's layout: a
# string of at most this many bytes, NUL-padded (one more byte, so C++ always has a terminator).
# ROS's own Header has an unbounded string; a longer one coming from ROS is refused by the codec.
FRAME_ID_MAX = 31

# The standard message types with a fixed layout, by their .msg name: (type, name[, default])
# per field, in ROS's order. THE definition: the C++ structs (standard_types.hpp), the Python
# codec's leaves and the ROS 2 interface package's dependencies all come from here. Types with
# sequences or unbounded strings (sensor_msgs/JointState, ...) are not here: a fixed-size struct
# cannot carry them.
_H = "std_msgs/Header"
_FRAME = f"string<={FRAME_ID_MAX}"
_XYZ = (("float64", "x"), ("float64", "y"), ("float64", "z"))
STANDARD_TYPES: dict[str, tuple[tuple[Any, ...], ...]] = {
    "builtin_interfaces/Time": (("int32", "sec"), ("uint32", "nanosec")),
    "builtin_interfaces/Duration": (("int32", "sec"), ("uint32", "nanosec")),
    "std_msgs/Header": (("builtin_interfaces/Time", "stamp"), (_FRAME, "frame_id")),
    "geometry_msgs/Vector3": _XYZ,
    "geometry_msgs/Point": _XYZ,
    "geometry_msgs/Point32": (("float32", "x"), ("float32", "y"), ("float32", "z")),
    # ROS's Quaternion.msg gives w the default 1 (the identity rotation); so do we.
    "geometry_msgs/Quaternion": _XYZ + (("float64", "w", 1.0),),
    "geometry_msgs/Pose2D": (("float64", "x"), ("float64", "y"), ("float64", "theta")),
    "geometry_msgs/Pose": (("geometry_msgs/Point", "position"), ("geometry_msgs/Quaternion", "orientation")),
    "geometry_msgs/Twist": (("geometry_msgs/Vector3", "linear"), ("geometry_msgs/Vector3", "angular")),
    "geometry_msgs/Accel": (("geometry_msgs/Vector3", "linear"), ("geometry_msgs/Vector3", "angular")),
    "geometry_msgs/Wrench": (("geometry_msgs/Vector3", "force"), ("geometry_msgs/Vector3", "torque")),
    "geometry_msgs/Transform": (
        ("geometry_msgs/Vector3", "translation"),
        ("geometry_msgs/Quaternion", "rotation"),
    ),
    "geometry_msgs/Vector3Stamped": ((_H, "header"), ("geometry_msgs/Vector3", "vector")),
    "geometry_msgs/PointStamped": ((_H, "header"), ("geometry_msgs/Point", "point")),
    "geometry_msgs/QuaternionStamped": ((_H, "header"), ("geometry_msgs/Quaternion", "quaternion")),
    "geometry_msgs/PoseStamped": ((_H, "header"), ("geometry_msgs/Pose", "pose")),
    "geometry_msgs/TwistStamped": ((_H, "header"), ("geometry_msgs/Twist", "twist")),
    "geometry_msgs/AccelStamped": ((_H, "header"), ("geometry_msgs/Accel", "accel")),
    "geometry_msgs/WrenchStamped": ((_H, "header"), ("geometry_msgs/Wrench", "wrench")),
    "geometry_msgs/TransformStamped": (
        (_H, "header"),
        (_FRAME, "child_frame_id"),
        ("geometry_msgs/Transform", "transform"),
    ),
}
STANDARD_SUPPORTED = ", ".join(STANDARD_TYPES)

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
    """One leaf of a message: a primitive, a fixed array of one, or a bounded string.

    A field of a standard type (``std_msgs/Header header``) is stored as its leaves, named by
    their path (``header.stamp.sec``, ``header.frame_id``), each remembering the declaration it
    came from (``decl``) so the schema text keeps the .msg's own line."""

    type: str  # the .msg primitive name, or "string" (bounded: count is its most bytes)
    name: str  # a plain name, or the dotted path of a leaf of a standard type
    count: int | None = None  # fixed array length (bytes of a string), None for a scalar
    default: Any = None  # the value a field not given gets (None: 0 / False / "")
    decl: str = ""  # "std_msgs/Header header" for the leaves of that line, "" for a plain field

    @property
    def primitive(self) -> PrimitiveType:
        return PRIMITIVES[self.type]

    @property
    def is_string(self) -> bool:
        return self.type == "string"

    @property
    def struct_code(self) -> str:
        if self.is_string:  # NUL-padded, one byte more than the bound: C++ gets a terminator
            return f"{(self.count or 0) + 1}s"
        return f"{self.count or ''}{self.primitive.struct_code}"

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.struct_code)

    @property
    def zero(self) -> Any:
        if self.default is not None:
            return self.default
        return "" if self.is_string else self.primitive.python(0)

    def schema_line(self) -> str:
        if self.decl:
            return self.decl
        if self.is_string:
            return f"string<={self.count} {self.name}"
        return f"{self.type}[{self.count}] {self.name}" if self.count else f"{self.type} {self.name}"


# ---- parsing ------------------------------------------------------------------------------------


_SEQUENCE_HINT = "a sequence (variable length); the loop's messages are fixed-size structs: use a fixed array type[N]"


def _parse_field(text: str, path: str, lineno: int) -> list[Field]:
    """The leaves of one .msg line (one for a primitive, several for a standard type)."""
    if "=" in text.replace("<=", ""):  # `<=` is a bound (type[<=N], string<=N), not a constant
        raise MsgError(path, lineno, f"constants are not supported: {text!r}")
    tokens = text.split()
    if len(tokens) == 1:
        raise MsgError(path, lineno, f"expected 'type name', got {text!r}")
    if len(tokens) > 2:
        raise MsgError(path, lineno, f"default values are not supported: {text!r}")
    type_text, name = tokens
    if not _NAME_RE.match(name):
        raise MsgError(
            path,
            lineno,
            f"bad field name '{name}' (lower case letters, digits and single underscores, starting with a letter)",
        )
    if name in _CPP_KEYWORDS:
        raise MsgError(path, lineno, f"field name '{name}' is a C++ keyword")
    return _leaves(type_text, name, path, lineno, decl="")


def _leaves(type_text: str, name: str, path: str, lineno: int, decl: str) -> list[Field]:
    string = re.fullmatch(r"(w?string)(?:<=([0-9]+))?", type_text)
    if string:
        if string[1] == "wstring":
            raise MsgError(path, lineno, f"'{type_text} {name}': wstring is not supported (use string<=N)")
        if string[2] is None:
            raise MsgError(
                path,
                lineno,
                f"'{type_text} {name}': an unbounded string cannot be carried by the loop's fixed-size "
                "messages; use a bounded one, string<=N (N bytes at most)",
            )
        bound = int(string[2])
        if bound < 1:
            raise MsgError(path, lineno, f"'{type_text}': the bound must be at least 1")
        return [Field("string", name, bound, decl=decl)]
    match = _TYPE_RE.match(type_text)
    if match is None:
        raise MsgError(path, lineno, f"cannot read type {type_text!r}")
    base = match["base"]
    if match["array"] and (match["bound"] or not match["size"]):
        raise MsgError(path, lineno, f"'{type_text}' is {_SEQUENCE_HINT} (only fixed-size arrays are supported)")
    if base in STANDARD_TYPES:
        if match["array"]:
            raise MsgError(
                path, lineno, f"'{type_text}': arrays of message types are not supported; declare the fields one by one"
            )
        leaves: list[Field] = []
        for spec in STANDARD_TYPES[base]:
            sub_type, sub_name = spec[0], spec[1]
            for leaf in _leaves(sub_type, sub_name, path, lineno, decl=decl):
                default = spec[2] if len(spec) > 2 else leaf.default
                leaves.append(Field(leaf.type, f"{name}.{leaf.name}", leaf.count, default, decl or f"{base} {name}"))
        return leaves
    if base not in PRIMITIVES:
        if "/" in base or base[0].isupper():
            hint = " (write std_msgs/Header)" if base == "Header" else ""
            raise MsgError(
                path,
                lineno,
                f"nested message type '{base}' is not supported{hint}: the loop's messages take the "
                f"fixed-layout standard types ({STANDARD_SUPPORTED}) and {SUPPORTED}",
            )
        raise MsgError(path, lineno, f"unsupported type '{base}' (supported: {SUPPORTED}, string<=N)")
    count: int | None = None
    if match["array"]:
        count = int(match["size"])
        if count < 1:
            raise MsgError(path, lineno, f"'{type_text}': array length must be at least 1")
    return [Field(base, name, count, decl=decl)]


def parse_msg_text(text: str, path: str | Path = "<msg>") -> list[Field]:
    """Fields of one .msg text, in order. Raises MsgError naming path and line."""
    path = str(path)
    fields: list[Field] = []
    first_line: dict[str, int] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        leaves = _parse_field(line, path, lineno)
        top = leaves[0].name.split(".", 1)[0]
        if top in first_line:
            raise MsgError(path, lineno, f"duplicate field '{top}' (first on line {first_line[top]})")
        first_line[top] = lineno
        fields.extend(leaves)
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
    """The normalised schema stored in shared memory: one ``type name`` per .msg line (a
    standard type's leaves give their declaration once)."""
    lines: list[str] = []
    for f in fields:
        line = f.schema_line()
        if not (f.decl and lines and lines[-1] == line):
            lines.append(line)
    return "\n".join(lines)


def standard_types_used(fields: Iterable[Field]) -> list[str]:
    """The standard types a message's lines name (``std_msgs/Header``), in order, once each."""
    out: list[str] = []
    for f in fields:
        if f.decl:
            t = f.decl.split()[0]
            if t not in out:
                out.append(t)
    return out


def parse_schema(text: str) -> list[Field]:
    return parse_msg_text(text, "<schema>")


# ---- the Python codec ---------------------------------------------------------------------------


class Codec:
    """Packs and unpacks one message exactly as the generated ``#pragma pack(1)`` struct lays it out."""

    def __init__(self, schema: str | Iterable[Field]) -> None:
        self.fields: list[Field] = parse_schema(schema) if isinstance(schema, str) else list(schema)
        self._by_name = {f.name: f for f in self.fields}
        self._struct = struct.Struct("<" + "".join(f.struct_code for f in self.fields))
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
            if f.is_string:
                flat.append(_string_bytes(f, f.zero if v is None else v))
                continue
            if f.count is None:
                flat.append(f.zero if v is None else v)
                continue
            items = [f.zero] * f.count if v is None else list(v)
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
            if f.is_string:
                # Up to the first NUL: the loop's C++ may leave bytes after it (a shorter string).
                out[f.name] = flat[at].split(b"\0", 1)[0].decode("utf-8", "replace")
                at += 1
            elif f.count is None:
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
        if f.is_string:
            return text
        if f.count is None:
            return _parse_scalar(f, text)
        parts = [p for p in text.strip().strip("[]").split(",") if p.strip()]
        return [_parse_scalar(f, p) for p in parts]


def _string_bytes(f: Field, value: Any) -> bytes:
    if not isinstance(value, str):
        raise ValueError(f"field {f.name} (string<={f.count}): expected text, got {value!r}")
    data = value.encode("utf-8")
    if len(data) > (f.count or 0):
        # Refused, not cut: a frame name cut in two would name another frame.
        raise ValueError(
            f"field {f.name}: {value[:40]!r} is {len(data)} bytes; the loop's layout holds at most {f.count} "
            f"(string<={f.count})"
        )
    return data


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


STANDARD_HEADER = Path("xrf2_msgs") / "msg" / "standard_types.hpp"


def _cpp_type_name(msg_type: str) -> str:
    """builtin_interfaces/Time -> builtin_interfaces::msg::Time (rosidl's C++ name)."""
    package, name = msg_type.split("/")
    return f"{package}::msg::{name}"


def _cpp_decl(type_text: str, name: str, default: Any = None) -> str:
    """One member of a generated struct from a .msg type: a primitive, a fixed array of one, a
    bounded string or a standard type."""
    if type_text in STANDARD_TYPES:
        return f"{_cpp_type_name(type_text)} {name};"
    if type_text.startswith("string<="):
        return f"::xrf2_msgs::msg::BoundedString<{type_text[len('string<=') :]}> {name};"
    base, _, rest = type_text.partition("[")
    cpp = PRIMITIVES[base].cpp
    if rest:
        return f"std::array<{cpp}, {rest.rstrip(']')}> {name}{{}};"
    init = default if default is not None else ("false" if cpp == "bool" else "0")
    return f"{cpp} {name} = {init};"


def _cpp_member(f: Field) -> str:
    if f.decl:  # the whole standard-type field, once for its leaves
        type_text, name = f.decl.split()
        return "    " + _cpp_decl(type_text, name)
    if f.is_string:
        return "    " + _cpp_decl(f"string<={f.count}", f.name)
    return "    " + _cpp_decl(f"{f.type}[{f.count}]" if f.count else f.type, f.name)


def generate_standard_header() -> str:
    """standard_types.hpp: the fixed-layout standard messages as packed structs with rosidl's
    names (std_msgs::msg::Header, geometry_msgs::msg::Pose, ...) and field names, plus the bounded
    string their frame names use. Generated from STANDARD_TYPES, like the project's messages."""
    blocks = []
    for msg_type, specs in STANDARD_TYPES.items():
        package, name = msg_type.split("/")
        members = "\n".join("    " + _cpp_decl(spec[0], spec[1], spec[2] if len(spec) > 2 else None) for spec in specs)
        blocks.append(
            f"namespace {package} {{\nnamespace msg {{\nstruct {name} {{\n{members}\n}};\n}}  // namespace msg\n}}  // namespace {package}"
        )
    body = "\n\n".join(blocks)
    return f"""// Generated by xrflab/msgdef.py. Do not edit.
// The standard ROS 2 message types a loop message may use, with a fixed layout: ROS's names and
// field names (msg.header.stamp.sec), packed like the project's messages. ROS's Header.frame_id is
// an unbounded string; here it is a BoundedString<{FRAME_ID_MAX}> (no allocation in the loop).
#ifndef XRF2_MSGS__MSG__STANDARD_TYPES_HPP
#define XRF2_MSGS__MSG__STANDARD_TYPES_HPP

#include <array>
#include <cstddef>
#include <cstdint>

namespace xrf2_msgs {{
namespace msg {{

// At most N bytes of text, NUL-padded in N + 1 (always terminated). Assigning a longer text keeps
// its first N bytes: the loop cannot report an error, so assign() says whether it all fit.
template <std::size_t N>
struct BoundedString {{
    char data[N + 1] = {{}};

    bool assign(const char *text)
    {{
        std::size_t i = 0;
        for (; text != nullptr && text[i] != '\\0' && i < N; ++i) data[i] = text[i];
        const bool fit = text == nullptr || text[i] == '\\0';
        for (std::size_t j = i; j <= N; ++j) data[j] = '\\0';
        return fit;
    }}
    BoundedString &operator=(const char *text)
    {{
        assign(text);
        return *this;
    }}
    const char *c_str() const {{ return data; }}
    std::size_t size() const
    {{
        std::size_t i = 0;
        while (i < N && data[i] != '\\0') ++i;
        return i;
    }}
    bool empty() const {{ return data[0] == '\\0'; }}
    static constexpr std::size_t max_size() {{ return N; }}
    bool operator==(const char *text) const
    {{
        std::size_t i = 0;
        for (; i < N && data[i] != '\\0'; ++i)
            if (text == nullptr || text[i] != data[i]) return false;
        return text != nullptr && text[i] == '\\0';
    }}
    bool operator!=(const char *text) const {{ return !(*this == text); }}
}};

}}  // namespace msg
}}  // namespace xrf2_msgs

#pragma pack(push, 1)
{body}
#pragma pack(pop)

#endif  // XRF2_MSGS__MSG__STANDARD_TYPES_HPP
"""


def standard_alias_headers() -> dict[Path, str]:
    """rosidl's header paths (std_msgs/msg/header.hpp, ...), each including standard_types.hpp,
    so a student's `#include <geometry_msgs/msg/pose.hpp>` finds the loop's type."""
    out = {}
    for msg_type in STANDARD_TYPES:
        package, name = msg_type.split("/")
        out[Path(package) / "msg" / f"{snake_case(name)}.hpp"] = (
            f"// Generated by xrflab/msgdef.py: {msg_type} for the loop (see xrf2_msgs/msg/standard_types.hpp).\n"
            "#pragma once\n#include <xrf2_msgs/msg/standard_types.hpp>\n"
        )
    return out


def generate_header(message: str, fields: list[Field], source: str = "") -> str:
    schema = schema_text(fields).replace("\n", "\\n")
    guard = f"XRF2_MSGS__MSG__{snake_case(message).upper()}_HPP"
    size = sum(f.size for f in fields)
    members = "\n".join(dict.fromkeys(_cpp_member(f) for f in fields))  # a standard type's leaves: once
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

#include <xrf2_msgs/msg/standard_types.hpp>

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
    standard = out_dir / STANDARD_HEADER
    _write_if_changed(standard, generate_standard_header())
    for alias, text in standard_alias_headers().items():
        _write_if_changed(out_dir / alias, text)
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
