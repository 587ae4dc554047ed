"""The .msg toolchain: parsing, errors that name file and line, generated C++ vs the Python codec."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from xrflab import msgdef
from xrflab.msgdef import Codec, Field, MsgError

ROS2XENO = "# setpoints from ROS\nfloat64 steer_left\nfloat64 steer_right   # rad/s\n"
XENO2ROS = "float64 pos_left\nfloat64 pos_right"  # no final newline, as students' files often are

# Every supported type, arrays included, in an order that would need padding if not packed.
ALL_TYPES = """
bool flag
float64 x
byte b
char c
int8 i8
uint8 u8
int16 i16
uint16 u16
int32 i32
uint32 u32
int64 i64
uint64 u64
float32 f32
float64 f64
int16[3] triple
bool[2] pair
float64[4] quad
"""

# A real project's start (issue 31): standard types, with a bounded string and the leaves' offsets
# that only a packed nested layout gives.
STANDARD = """std_msgs/Header header
uint8 flag
geometry_msgs/Pose pose
geometry_msgs/Twist twist
builtin_interfaces/Duration age
geometry_msgs/Point32 p32
string<=5 tag
geometry_msgs/TransformStamped tf
float64 pos_left
"""


def write_project_msgs(msg_dir: Path, ros2xeno: str = ROS2XENO, xeno2ros: str = XENO2ROS) -> Path:
    msg_dir.mkdir(parents=True, exist_ok=True)
    (msg_dir / "Ros2Xeno.msg").write_text(ros2xeno)
    (msg_dir / "Xeno2Ros.msg").write_text(xeno2ros)
    return msg_dir


def test_parse_comments_blank_lines_and_missing_newline() -> None:
    fields = msgdef.parse_msg_text(ROS2XENO + "\n\n   # trailing comment\nint32[4] counts", "x.msg")
    assert fields == [
        Field("float64", "steer_left"),
        Field("float64", "steer_right"),
        Field("int32", "counts", 4),
    ]
    assert msgdef.schema_text(fields) == "float64 steer_left\nfloat64 steer_right\nint32[4] counts"
    assert msgdef.parse_msg_text("", "empty.msg") == []


@pytest.mark.parametrize(
    "line, message",
    [
        ("string name", "an unbounded string cannot be carried by the loop's fixed-size messages; use a bounded one"),
        ("wstring name", "wstring is not supported"),
        ("string<=0 name", "the bound must be at least 1"),
        ("float64[] values", "'float64[]' is a sequence (variable length)"),
        ("float64[<=4] values", "'float64[<=4]' is a sequence"),
        ("int32 nums[3]", "bad field name 'nums[3]'"),
        ("float64[0] values", "at least 1"),
        ("int32 X=1", "constants are not supported"),
        ("int32 LIMIT = 10", "constants are not supported"),
        ("float64 gain 1.5", "default values are not supported"),
        ("sensor_msgs/JointState joints", "nested message type 'sensor_msgs/JointState' is not supported"),
        ("Header header", "nested message type 'Header' is not supported (write std_msgs/Header)"),
        ("geometry_msgs/Point[3] points", "arrays of message types are not supported"),
        ("std_msgs/Header[] headers", "is a sequence"),
        ("std_msgs/Header steer_left", "duplicate field 'steer_left' (first on line 2)"),
        ("float64 Steer", "bad field name 'Steer'"),
        ("float64 2fast", "bad field name '2fast'"),
        ("float64 a__b", "bad field name 'a__b'"),
        ("float64 trailing_", "bad field name 'trailing_'"),
        ("int32 class", "C++ keyword"),
        ("float64", "expected 'type name'"),
        ("float64[3 x", "cannot read type"),
        ("float64 steer_left", "duplicate field 'steer_left' (first on line 2)"),
    ],
)
def test_bad_input_names_file_and_line(tmp_path: Path, line: str, message: str) -> None:
    path = tmp_path / "Ros2Xeno.msg"
    path.write_text("# header comment\nfloat64 steer_left\n\n" + line + "\n")
    with pytest.raises(MsgError) as err:
        msgdef.parse_msg_file(path)
    assert str(err.value).startswith(f"{path}:4: ")
    assert message in str(err.value)
    assert err.value.line == 4 and err.value.path == str(path)


def test_error_format_matches_the_documented_example() -> None:
    with pytest.raises(MsgError) as err:
        msgdef.parse_msg_text("float64 a\nfloat64 b\nstring name", "msg/Ros2Xeno.msg")
    assert str(err.value).startswith("msg/Ros2Xeno.msg:3: 'string name': an unbounded string cannot be carried")


def test_too_large_message_is_rejected() -> None:
    with pytest.raises(MsgError, match="at most 512"):
        msgdef.parse_msg_text("float64[65] big", "big.msg")
    assert Codec("float64[64] ok").size == 512


def test_snake_case_like_ros() -> None:
    assert msgdef.snake_case("Ros2Xeno") == "ros2_xeno"
    assert msgdef.snake_case("Xeno2Ros") == "xeno2_ros"
    assert msgdef.snake_case("HTTPServer") == "http_server"
    assert msgdef.snake_case("JointState") == "joint_state"
    assert msgdef.header_relpath("Ros2Xeno") == Path("xrf2_msgs/msg/ros2_xeno.hpp")


def test_codec_round_trip_partial_and_unknown() -> None:
    codec = Codec(msgdef.schema_text(msgdef.parse_msg_text(ALL_TYPES)))
    assert codec.size == 1 + 8 + 1 + 1 + 1 + 1 + 2 + 2 + 4 + 4 + 8 + 8 + 4 + 8 + 6 + 2 + 32
    values = {
        "flag": True,
        "x": -1.25,
        "b": 255,
        "c": 65,
        "i8": -128,
        "u8": 200,
        "i16": -32768,
        "u16": 65535,
        "i32": -(2**31),
        "u32": 2**32 - 1,
        "i64": -(2**63),
        "u64": 2**64 - 1,
        "f32": 0.5,
        "f64": math.pi,
        "triple": [1, -2, 3],
        "pair": [False, True],
        "quad": [0.0, 1.0, 2.0, 3.0],
    }
    assert codec.decode(codec.encode(values)) == values
    partial = codec.decode(codec.encode({"x": 2.0}))
    assert partial["x"] == 2.0 and partial["flag"] is False and partial["triple"] == [0, 0, 0]
    with pytest.raises(ValueError, match="unknown field.*nope.*valid fields: flag, x, b"):
        codec.encode({"nope": 1})
    with pytest.raises(ValueError, match="expected 3 values"):
        codec.encode({"triple": [1, 2]})
    with pytest.raises(ValueError):
        codec.encode({"u8": 256})
    with pytest.raises(ValueError, match="need"):
        codec.decode(b"\0")
    assert codec.decode(codec.encode(values) + b"padding") == values  # the loop may copy more


@given(st.floats(allow_nan=False, width=64), st.integers(-(2**31), 2**31 - 1), st.booleans())
def test_codec_round_trip_property(x: float, n: int, flag: bool) -> None:
    codec = Codec("float64 x\nint32 n\nbool flag")
    assert codec.decode(codec.encode({"x": x, "n": n, "flag": flag})) == {"x": x, "n": n, "flag": flag}


def test_parse_value_from_text() -> None:
    codec = Codec("float64 x\nint32 n\nbool on\nuint8[3] rgb")
    assert codec.parse_value("x", "1.5") == 1.5
    assert codec.parse_value("n", "0x10") == 16
    assert codec.parse_value("on", "true") is True and codec.parse_value("on", "0") is False
    assert codec.parse_value("rgb", "[1, 2,3]") == [1, 2, 3]
    with pytest.raises(ValueError, match="field n"):
        codec.parse_value("n", "1.5")
    with pytest.raises(ValueError, match="valid fields"):
        codec.parse_value("y", "1")


def test_generate_project_headers(tmp_path: Path) -> None:
    msg_dir = write_project_msgs(tmp_path / "msg")
    out = tmp_path / "gen"
    written = msgdef.generate_project_headers(msg_dir, out)
    assert written == [out / "xrf2_msgs/msg/ros2_xeno.hpp", out / "xrf2_msgs/msg/xeno2_ros.hpp"]
    text = written[0].read_text()
    assert "namespace xrf2_msgs {\nnamespace msg {" in text
    assert "#pragma pack(push, 1)\nstruct Ros2Xeno {\n    double steer_left = 0;\n    double steer_right = 0;" in text
    assert 'XRF_SCHEMA = "float64 steer_left\\nfloat64 steer_right";' in text
    assert "static_assert(sizeof(Ros2Xeno) <= 512" in text
    # Unchanged input leaves the file alone, so a rebuild does not recompile the controller.
    mtime = written[0].stat().st_mtime_ns
    msgdef.generate_project_headers(msg_dir, out)
    assert written[0].stat().st_mtime_ns == mtime


def test_missing_folder_or_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(MsgError, match="message folder not found"):
        msgdef.generate_project_headers(tmp_path / "nope", tmp_path / "out")
    (tmp_path / "msg").mkdir()
    (tmp_path / "msg" / "Ros2Xeno.msg").write_text(ROS2XENO)
    with pytest.raises(MsgError, match=r"Xeno2Ros\.msg: missing"):
        msgdef.generate_project_headers(tmp_path / "msg", tmp_path / "out")


def _run_script(*args: str) -> subprocess.CompletedProcess:
    script = Path(msgdef.__file__)
    return subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True)


def test_script_mode(tmp_path: Path) -> None:
    msg_dir = write_project_msgs(tmp_path / "msg")
    ok = _run_script("--msg-dir", str(msg_dir), "--out", str(tmp_path / "gen"))
    assert ok.returncode == 0, ok.stderr
    assert (tmp_path / "gen/xrf2_msgs/msg/xeno2_ros.hpp").is_file()
    (msg_dir / "Xeno2Ros.msg").write_text("float64 a\nstring name\n")
    bad = _run_script("--msg-dir", str(msg_dir), "--out", str(tmp_path / "gen"))
    assert bad.returncode == 1
    assert bad.stderr.strip().startswith(f"{msg_dir / 'Xeno2Ros.msg'}:2: 'string name': an unbounded string")
    missing = _run_script("--msg-dir", str(tmp_path / "absent"), "--out", str(tmp_path / "gen"))
    assert missing.returncode == 1 and "absent" in missing.stderr and "not found" in missing.stderr


LAYOUT_MAIN = """
#include <cstddef>
#include <cstdio>
#include "xrf2_msgs/msg/ros2_xeno.hpp"
#include "xrf2_msgs/msg/xeno2_ros.hpp"
using xrf2_msgs::msg::Ros2Xeno;
using xrf2_msgs::msg::Xeno2Ros;
int main() {
    std::printf("{\\"Ros2Xeno\\": {\\"sizeof\\": %zu, \\"offsets\\": {", sizeof(Ros2Xeno));
    %(ros_offsets)s
    std::printf("}}, \\"Xeno2Ros\\": {\\"sizeof\\": %zu, \\"offsets\\": {", sizeof(Xeno2Ros));
    %(xeno_offsets)s
    std::printf("}}, \\"schema\\": \\"%s\\"}\\n", Ros2Xeno::XRF_SCHEMA[0] ? "ok" : "");
    Ros2Xeno r;  // members are zero-initialised by their default member initialisers
    return r.%(first)s == 0 ? 0 : 1;
}
"""


def _offset_prints(struct: str, fields: list[Field]) -> str:
    parts = []
    for i, f in enumerate(fields):
        sep = ", " if i else ""
        parts.append(f'std::printf("{sep}\\"{f.name}\\": %zu", offsetof({struct}, {f.name}));')
    return "\n    ".join(parts)


@pytest.mark.parametrize("xeno2ros", [XENO2ROS, STANDARD], ids=["primitives", "standard-types"])
def test_generated_header_layout_matches_codec(tmp_path: Path, xeno2ros: str) -> None:
    compiler = shutil.which("g++")
    assert compiler, "g++ is needed (build-essential)"
    ros_fields = msgdef.parse_msg_text(ALL_TYPES)
    xeno_fields = msgdef.parse_msg_text(xeno2ros)
    msg_dir = write_project_msgs(tmp_path / "msg", ALL_TYPES, xeno2ros)
    msgdef.generate_project_headers(msg_dir, tmp_path / "gen")
    source = tmp_path / "layout.cpp"
    source.write_text(
        LAYOUT_MAIN.replace("%(ros_offsets)s", _offset_prints("Ros2Xeno", ros_fields))
        .replace("%(xeno_offsets)s", _offset_prints("Xeno2Ros", xeno_fields))
        .replace("%(first)s", ros_fields[1].name)
    )
    exe = tmp_path / "layout"
    build = subprocess.run(
        [
            compiler,
            "-std=c++17",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-Wno-invalid-offsetof",
            "-I",
            str(tmp_path / "gen"),
            str(source),
            "-o",
            str(exe),
        ],
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
    layout = json.loads(run.stdout)
    for name, fields in (("Ros2Xeno", ros_fields), ("Xeno2Ros", xeno_fields)):
        codec = Codec(fields)
        assert layout[name]["sizeof"] == codec.size
        assert layout[name]["offsets"] == codec.offsets()
    assert layout["schema"] == "ok"


def test_oversized_struct_fails_to_compile(tmp_path: Path) -> None:
    """The header's own static_assert guards the channel size even if the generator is bypassed."""
    compiler = shutil.which("g++")
    assert compiler
    header = msgdef.generate_header("Big", [Field("float64", "v", 65)])
    (tmp_path / "big.hpp").write_text(header)
    (tmp_path / msgdef.STANDARD_HEADER).parent.mkdir(parents=True)
    (tmp_path / msgdef.STANDARD_HEADER).write_text(msgdef.generate_standard_header())
    (tmp_path / "main.cpp").write_text('#include "big.hpp"\nint main() { return 0; }\n')
    build = subprocess.run(
        [compiler, "-std=c++17", "-fsyntax-only", "-I", str(tmp_path), str(tmp_path / "main.cpp")],
        capture_output=True,
        text=True,
    )
    assert build.returncode != 0 and "larger than the 512 bytes" in build.stderr


def test_standard_types_are_leaves_named_by_their_path() -> None:
    fields = msgdef.parse_msg_text("std_msgs/Header header\ngeometry_msgs/Quaternion q\nstring<=4 tag")
    assert [(f.type, f.name, f.count) for f in fields] == [
        ("int32", "header.stamp.sec", None),
        ("uint32", "header.stamp.nanosec", None),
        ("string", "header.frame_id", msgdef.FRAME_ID_MAX),
        ("float64", "q.x", None),
        ("float64", "q.y", None),
        ("float64", "q.z", None),
        ("float64", "q.w", None),
        ("string", "tag", 4),
    ]
    # The schema keeps the .msg's own lines (what the loop publishes, what ROS builds from).
    assert msgdef.schema_text(fields) == "std_msgs/Header header\ngeometry_msgs/Quaternion q\nstring<=4 tag"
    codec = Codec(msgdef.schema_text(fields))
    assert codec.size == 4 + 4 + 32 + 4 * 8 + 5
    values = codec.decode(codec.encode({"header.frame_id": "base", "header.stamp.sec": 7, "tag": "abcd"}))
    assert values["header.frame_id"] == "base" and values["tag"] == "abcd" and values["header.stamp.sec"] == 7
    assert values["q.w"] == 1.0  # ROS's default for Quaternion.w, not 0
    with pytest.raises(ValueError, match=r"field header\.frame_id: .* is 32 bytes; the loop's layout holds at most 31"):
        codec.encode({"header.frame_id": "x" * 32})
    with pytest.raises(ValueError, match="expected text"):
        codec.encode({"tag": 5})
    assert codec.parse_value("tag", "ab") == "ab"


def test_standard_types_cpp_names_and_bounded_string(tmp_path: Path) -> None:
    """The loop's C++ uses ROS's type and field names; a frame name is assigned from text and
    cut at the bound (assign() says so): nothing allocates."""
    compiler = shutil.which("g++")
    assert compiler
    msg_dir = write_project_msgs(tmp_path / "msg", "std_msgs/Header header\ngeometry_msgs/Twist cmd\n", STANDARD)
    msgdef.generate_project_headers(msg_dir, tmp_path / "gen")
    (tmp_path / "main.cpp").write_text(
        '#include <cstdio>\n#include <std_msgs/msg/header.hpp>\n#include "xrf2_msgs/msg/ros2_xeno.hpp"\n'
        "int main() { xrf2_msgs::msg::Ros2Xeno m{}; m.header.stamp.sec = 5; m.cmd.linear.x = 1.5;\n"
        '  std_msgs::msg::Header h = m.header; bool fit = h.frame_id.assign("base_link");\n'
        '  bool cut = h.frame_id.assign("0123456789012345678901234567890123456789");\n'
        '  std::printf("%d %g %d %d %zu %s\\n", h.stamp.sec, m.cmd.linear.x, fit, cut, h.frame_id.size(),'
        ' h.frame_id == "0123456789012345678901234567890" ? "eq" : "ne"); }\n'
    )
    exe = tmp_path / "main"
    build = subprocess.run(
        [
            compiler,
            "-std=c++17",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-I",
            str(tmp_path / "gen"),
            str(tmp_path / "main.cpp"),
            "-o",
            str(exe),
        ],
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, build.stderr
    assert subprocess.run([str(exe)], capture_output=True, text=True).stdout.split() == [
        "5",
        "1.5",
        "1",
        "0",
        "31",
        "eq",
    ]
