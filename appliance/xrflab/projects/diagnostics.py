"""What a failed build tells the student: the diagnostics in its log and a one-line summary.

The build log is the output of cmake, the compiler, the linker and the ``.msg`` generator; the
build page lists their ``file:line`` errors and warnings (``parse_diagnostics``: file names
relative to the project, or marked as the build folder's) and the build's result line names the
first error, or a limit of the sandbox it ran into (``summarise``: out of memory, too many
processes, no network, ...), in words a student can act on.
"""

from __future__ import annotations

import os
import re
from dataclasses import asdict
from pathlib import Path
from typing import TypedDict

from ..build import cmake_message
from .sandbox_config import SandboxConfig


class _DiagnosticFields(TypedDict):
    file: str  # relative to the project; "(build) ..." in the build folder; "" for the linker's
    line: int | None
    col: int | None
    kind: str  # error, warning, note
    message: str
    in_project: bool
    source: str  # compiler, cmake, msg, linker


class Diagnostic(_DiagnosticFields, total=False):
    context: str  # the linker's: the object or source it was linking
    log_line: int  # the line of the build log it came from


_DIAG_RE = re.compile(
    r"^(?P<file>[^\s:][^:]*?):(?P<line>\d+):(?:(?P<col>\d+):)?\s*(?P<kind>fatal error|error|warning|note):\s*(?P<msg>.*)$"
)
_CMAKE_RE = re.compile(
    r"^CMake (?P<kind>Error|Warning)(?: \(dev\))? at (?P<file>[^:]+):(?P<line>\d+)(?: \((?P<cmd>[^)]*)\))?:"
)
_MSG_RE = re.compile(r"^(?:.*?error: )?(?P<file>[^\s:]+\.msg):(?P<line>\d+):\s*(?P<msg>.*)$")
_LINK_RE = re.compile(r"(undefined reference to [`'].*?'|multiple definition of [`'].*?'|cannot find -l\S+)")


def parse_diagnostics(lines: list[str], src: Path, build_dir: Path) -> list[Diagnostic]:
    """file:line[:col] errors and warnings of the compiler, CMake and the .msg generator."""
    out: list[Diagnostic] = []
    seen: set[tuple[str, int | None, int | None, str]] = set()
    src_s, build_s = str(src.resolve()), str(build_dir.resolve())

    def rel(path: str) -> tuple[str, bool]:
        p = path.strip()
        if p.startswith(src_s + "/"):
            return p[len(src_s) + 1 :], True
        if p.startswith(build_s + "/"):
            return "(build) " + p[len(build_s) + 1 :], False
        if not os.path.isabs(p) and not p.startswith(".."):
            return p, (src / p).is_file()
        return p, False

    for i, line in enumerate(lines):
        m = _DIAG_RE.match(line)
        d: Diagnostic | None = None
        if m and not line.startswith("$ "):
            f, inside = rel(m.group("file"))
            kind = "error" if m.group("kind") == "fatal error" else m.group("kind")
            d = {
                "file": f,
                "line": int(m.group("line")),
                "col": int(m.group("col")) if m.group("col") else None,
                "kind": kind,
                "message": m.group("msg"),
                "in_project": inside,
                "source": "compiler",
            }
        elif m := _CMAKE_RE.match(line):
            f, inside = rel(m.group("file"))
            msg = cmake_message(lines, i)  # the whole indented message, not its first line
            d = {
                "file": f,
                "line": int(m.group("line")),
                "col": None,
                "kind": m.group("kind").lower(),
                "message": msg,
                "in_project": inside,
                "source": "cmake",
            }
        elif (m := _MSG_RE.match(line)) and ".msg:" in line:
            f, inside = rel(m.group("file"))
            d = {
                "file": f,
                "line": int(m.group("line")),
                "col": None,
                "kind": "error",
                "message": m.group("msg"),
                "in_project": inside,
                "source": "msg",
            }
        elif m := _LINK_RE.search(line):
            d = {
                "file": "",
                "line": None,
                "col": None,
                "kind": "error",
                "message": "link error: " + m.group(1),
                "in_project": False,
                "source": "linker",
            }
            pre = line.split(":(", 1)[0]
            if pre.endswith((".cpp", ".c", ".cc", ".o")) or ":(" in line:
                d["context"] = pre
        if d:
            key = (d["file"], d["line"], d["col"], d["message"])
            if key not in seen:
                seen.add(key)
                d["log_line"] = i
                out.append(d)
    return out


_HINTS = [
    (
        re.compile(r"MemoryError|std::bad_alloc|virtual memory exhausted|Cannot allocate memory|out of memory", re.I),
        "the build ran out of memory (limit {memory_mb} MB per process)",
    ),
    (
        re.compile(r"Resource temporarily unavailable|fork: retry|Cannot fork|can't fork|fork failed", re.I),
        "the build started too many processes (limit {nproc})",
    ),
    (
        re.compile(
            r"Could not resolve host|Couldn't resolve|Network is unreachable|Name or service not known|"
            r"Temporary failure in name resolution|file DOWNLOAD|Couldn't connect",
            re.I,
        ),
        "builds have no network: everything the project needs must be in the project folder",
    ),
    (re.compile(r"File size limit exceeded", re.I), "the build wrote a file over {fsize_mb} MB"),
    (
        re.compile(r"(Permission denied|Read-only file system)", re.I),
        "a build may only write inside its own build folder",
    ),
]


def summarise(
    ok: bool,
    lines: list[str],
    diags: list[Diagnostic],
    cfg: SandboxConfig,
    timed_out: bool,
    error: str,
    duration: float,
) -> str:
    if ok:
        return f"built in {duration:.1f} s"
    hint = ""
    text = "\n".join(lines[-400:])
    for rx, msg in _HINTS:
        if rx.search(text):
            hint = msg.format(**asdict(cfg))
            break
    if timed_out:
        return (
            f"the build took longer than {cfg.timeout_s:.0f} s and was stopped (is something in the build "
            "waiting or looping?)" + (f" — {hint}" if hint else "")
        )
    first = next((d for d in diags if d["kind"] == "error"), None)
    if first and first["source"] == "linker":
        head = first["message"] + (f" (in {first['context']})" if first.get("context") else "")
    elif first:
        loc = f"{first['file']}:{first['line']}" + (f":{first['col']}" if first.get("col") else "")
        head = f"{loc}: {first['kind']}: {first['message']}"
    else:
        head = error or "the build failed"
    return f"{head} — {hint}" if hint and hint not in head else head
