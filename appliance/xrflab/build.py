"""Building rt_core and student controller projects.

Two entry points:

- ``ensure_rt_core()`` configures, builds and installs rt_core once per content hash into a
  cache prefix and returns that prefix (the ``CMAKE_PREFIX_PATH`` for ``find_package(XrfRt)``).
- ``build_project()`` builds a student project against it and returns the executable.

A project comes in one of two layouts:

- ``xrf``: its CMakeLists.txt uses ``find_package(XrfRt)`` + ``xrf_add_controller()``;
  built as it is.
- ``xrf2``: written for XRF2 (its CMakeLists.txt compiles ``../XRF2/XenoRosFramework`` and
  links evl/rclcpp as an ament package). Its C++ files are built unchanged against rt_core
  with a CMakeLists.txt we generate in the build folder; the project folder is never written.

Output streams line by line to ``log``; a failure raises ``BuildError`` carrying the tail of
the output so the user sees the compiler's or CMake's own message.
"""

from __future__ import annotations

import collections
import fcntl
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .tied import popen_tied

Log = Callable[[str], None]

REPO_ROOT = Path(__file__).resolve().parents[2]
LOG_TAIL_LINES = 200

# Files XRF2 shipped as framework sources. A project folder that carries a copy (some students
# copied the framework next to their code) must not compile it: rt_core provides these.
XRF2_FRAMEWORK_STEMS = {
    "XenoFrtLoop",
    "XenoFrtRosIco",
    "XenoFrt20Sim",
    "FullStateMachine",
    "XenoFrtLogger",
    "XenoFileHandler",
    "XenoFrtMonitor",
    "IcoIo",
    "XenoSpiControllerHandler",
    "XenoRosCommunication",
    "XenoRosDataBridge",
    "XenoRosCommandBridge",
    "configuration",
    "debug_settings",
    "ICommunication",
    "ICommunicationFullDuplex",
}
_CXX_SUFFIXES = (".cpp", ".cc", ".cxx", ".c")
_MAIN_RE = re.compile(r"^\s*int\s+main\s*\(", re.MULTILINE)
_SKIP_DIRS = {"build", "install", "log", ".git", "__pycache__", ".vscode", ".idea"}


class BuildError(Exception):
    """A build step failed. ``str()`` is the reason followed by the output's last lines."""

    def __init__(self, message: str, log_tail: str = "") -> None:
        self.message = message
        self.log_tail = log_tail
        super().__init__(f"{message}\n{log_tail}" if log_tail else message)


@dataclass
class BuildResult:
    executable: Path
    build_dir: Path
    layout: Literal["xrf", "xrf2"]
    taken: list[str] = field(default_factory=list)
    left_out: dict[str, str] = field(default_factory=dict)
    twenty_sim: dict | None = None


# ---------------------------------------------------------------------------------------
# running commands


_CMAKE_ERROR_RE = re.compile(r"^CMake Error(?: \(dev\))?(?: at [^:]+:\d+(?: \([^)]*\))?)?:\s*(?P<inline>.*)$")
CMAKE_MESSAGE_MAX = 600


def cmake_message(lines: list[str], at: int) -> str:
    """The text of the CMake error or warning whose head line is ``lines[at]``: CMake prints
    ``CMake Error at file:line (message):`` and then the message itself indented by two spaces,
    in paragraphs, until ``Call Stack`` or the next unindented line. One line, whitespace folded
    (CMake wraps at 80 columns), at most CMAKE_MESSAGE_MAX characters."""
    m = _CMAKE_ERROR_RE.match(lines[at].replace("CMake Warning", "CMake Error", 1))
    parts = [m["inline"].strip()] if m and m["inline"].strip() else []
    for line in lines[at + 1 :]:
        if line.startswith("Call Stack") or (line.strip() and not line.startswith((" ", "\t"))):
            break
        if line.strip():
            parts.append(line.strip())
    text = " ".join(" ".join(parts).split())
    return text if len(text) <= CMAKE_MESSAGE_MAX else text[: CMAKE_MESSAGE_MAX - 1] + "…"


def first_cmake_error(lines: list[str]) -> str:
    """The message of the first ``CMake Error`` in a configure's output, "" when there is none."""
    for i, line in enumerate(lines):
        if _CMAKE_ERROR_RE.match(line):
            return cmake_message(lines, i)
    return ""


def _run(cmd: list[str], log: Log, cwd: Path | None = None, what: str = "") -> list[str]:
    """Run ``cmd``, passing each output line to ``log`` as it arrives; return all lines.

    stderr is merged into stdout so errors appear in order with the lines around them.
    """
    log("$ " + " ".join(cmd))
    tail: collections.deque[str] = collections.deque(maxlen=LOG_TAIL_LINES)
    lines: list[str] = []
    env = dict(os.environ)
    env.setdefault("CLICOLOR_FORCE", "0")
    try:
        # close_fds (the default) and no stdin: cmake and the compilers get their output pipe only.
        # Tied to the process that asked (the appliance, or `xrf build`): no orphaned compiler.
        proc = popen_tied(
            cmd,
            death_signal=signal.SIGKILL,
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            errors="replace",
            bufsize=1,
            env=env,
        )
    except OSError as exc:
        raise BuildError(f"{what or cmd[0]}: cannot run {cmd[0]}: {exc}") from exc
    assert proc.stdout is not None
    for line in proc.stdout:
        line = line.rstrip("\n")
        tail.append(line)
        lines.append(line)
        log(line)
    rc = proc.wait()
    if rc != 0:
        # The one-line reason names CMake's own message, not only its "CMake Error at f:93 (message):".
        reason = first_cmake_error(lines)
        raise BuildError(
            f"{what or ' '.join(cmd)} failed (exit {rc})" + (f": {reason}" if reason else ""), "\n".join(tail)
        )
    return lines


def _drop_foreign_cache(build_dir: Path, log: Log) -> None:
    """A CMakeCache.txt made in another folder (a build/ committed with the project, a project
    copied or moved after a build) stops CMake ("CMakeCache.txt directory ... is different");
    its configuration is forgotten and the folder configured afresh."""
    cache = build_dir / "CMakeCache.txt"
    try:
        text = cache.read_text(errors="replace")
    except OSError:
        return
    m = re.search(r"^CMAKE_CACHEFILE_DIR:INTERNAL=(.*)$", text, re.MULTILINE)
    if m is None or Path(m.group(1).strip()).resolve() == build_dir.resolve():
        return
    log(f"{build_dir}: CMakeCache.txt was made in {m.group(1).strip()}; configuring afresh")
    cache.unlink()
    shutil.rmtree(build_dir / "CMakeFiles", ignore_errors=True)


def _generator_args(build_dir: Path) -> list[str]:
    # A build folder keeps the generator it was configured with; only choose for a new one.
    if (build_dir / "CMakeCache.txt").exists():
        return []
    return ["-G", "Ninja"] if shutil.which("ninja") else []


def _jobs() -> str:
    return str(max(1, (os.cpu_count() or 2)))


# ---------------------------------------------------------------------------------------
# rt_core


def _content_hash(paths: Iterable[Path]) -> str:
    """Hash of file names and contents under ``paths`` (build folders and caches skipped)."""
    h = hashlib.sha256()
    for root in paths:
        files = (
            [root]
            if root.is_file()
            else sorted(
                p
                for p in root.rglob("*")
                if p.is_file()
                and not any(part in _SKIP_DIRS or part.startswith("build") for part in p.relative_to(root).parts)
            )
        )
        for p in files:
            h.update(str(p.relative_to(root.parent)).encode())
            h.update(b"\0")
            h.update(p.read_bytes())
            h.update(b"\0")
    return h.hexdigest()[:16]


def _cache_root() -> Path:
    base = os.environ.get("XRF_CACHE_DIR")
    return Path(base) if base else Path.home() / ".cache" / "xrf-lab"


def ensure_rt_core(log: Log = print, source_root: Path | None = None) -> Path:
    """Build and install rt_core unless an install with the same content hash exists.

    Returns the install prefix. Concurrent callers (two builds started at once) serialise on
    a file lock; the second finds the first's install and reuses it.
    """
    root = Path(source_root) if source_root else REPO_ROOT
    rt_core = root / "rt_core"
    msgdef = root / "appliance" / "xrflab" / "msgdef.py"
    # Installed beside msgdef.py: the 20-sim parameter table generator (live tuning).
    twentysim_params = root / "appliance" / "xrflab" / "twentysim_params.py"
    for p in (rt_core / "CMakeLists.txt", msgdef, twentysim_params):
        if not p.exists():
            raise BuildError(f"{p}: not found (cannot build rt_core)")
    # The installed libevl is part of what gets built (the evl backend exists only with it):
    # installing or upgrading libevl must not reuse a posix-only build. XRF_EVL_PREFIX names
    # another libevl install than /usr/evl (CI's EVL look-alike, tests/rt_core/evl/lookalike).
    evl_prefix = Path(os.environ.get("XRF_EVL_PREFIX") or "/usr/evl")
    evl = evl_prefix / "lib" / "libevl.so"
    evl_tag = f"evl:{evl_prefix}:{evl.stat().st_mtime_ns}" if evl.exists() else "evl:none"
    digest = hashlib.sha256((_content_hash([rt_core, msgdef, twentysim_params]) + evl_tag).encode()).hexdigest()[:16]
    cache = _cache_root() / "rt_core"
    prefix = cache / digest
    done = prefix / ".xrf-complete"
    if done.exists():
        return prefix
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / f"{digest}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if done.exists():
            return prefix
        log(f"rt_core: building into {prefix} (content hash {digest})")
        shutil.rmtree(prefix, ignore_errors=True)
        work = cache / f"{digest}.build"
        shutil.rmtree(work, ignore_errors=True)
        _run(
            [
                "cmake",
                "-S",
                str(rt_core),
                "-B",
                str(work),
                *_generator_args(work),
                "-DCMAKE_BUILD_TYPE=RelWithDebInfo",
                f"-DCMAKE_INSTALL_PREFIX={prefix}",
                f"-DXRF_EVL_PREFIX={evl_prefix}",
                # Keep the library in lib/ on every distro: the prefix is private anyway.
                "-DCMAKE_INSTALL_LIBDIR=lib",
            ],
            log,
            what="rt_core configure",
        )
        _run(["cmake", "--build", str(work), "--parallel", _jobs()], log, what="rt_core build")
        _run(["cmake", "--install", str(work)], log, what="rt_core install")
        done.write_text(digest + "\n")
        shutil.rmtree(work, ignore_errors=True)
        log(f"rt_core: installed in {prefix}")
    return prefix


# ---------------------------------------------------------------------------------------
# project layouts


# The framework before XRF2: a loop class deriving from NativeBase (or Native20Sim for 20-sim
# code, preProc()/postProc() hooks) and messages in a ROS package custom_msgs. Its CMake stops at
# find_package(custom_msgs), which says nothing useful: recognised before CMake runs.
_PRE_XRF2_CLASS_RE = re.compile(r"(?::|,)\s*(?:public|protected|private)?\s*(Native20Sim|NativeBase)\b")
_PRE_XRF2_INCLUDE_RE = re.compile(r"#\s*include\s*[\"<](Native20Sim|NativeBase)\.h(?:pp)?[\">]")
_XRF2_CLASS_RE = re.compile(r"\bXenoFrt(?:Loop|RosIco|20Sim)\b")
_CUSTOM_MSGS_RE = re.compile(r"find_package\s*\(\s*custom_msgs\b")
_SOURCE_SCAN_LIMIT = 512 * 1024  # bytes read per file: generated 20-sim code can be large


def pre_xrf2_evidence(project_dir: Path) -> list[str]:
    """Where a project shows it is written for the framework before XRF2 ([] when it is not):
    ``src/MyApp.h: class ... : public Native20Sim``, ``CMakeLists.txt: find_package(custom_msgs)``.
    A project that also uses XRF2's classes is XRF2 (it may keep an old file around)."""
    found: list[str] = []
    custom_msgs = False
    for path in _walk(project_dir):
        if path.suffix.lower() in (".h", ".hpp", ".hh", ".cpp", ".cc", ".cxx"):
            try:
                with open(path, "rb") as f:
                    text = f.read(_SOURCE_SCAN_LIMIT).decode("utf-8", "replace")
            except OSError:  # a dangling link, an unreadable file: not evidence either way
                continue
            if _XRF2_CLASS_RE.search(text):
                return []
            m = _PRE_XRF2_CLASS_RE.search(text) or _PRE_XRF2_INCLUDE_RE.search(text)
            if m and len(found) < 3:
                line = text.count("\n", 0, m.start()) + 1
                what = f"derives from {m[1]}" if m.re is _PRE_XRF2_CLASS_RE else f"includes {m[1]}.h"
                found.append(f"{_rel(path, project_dir)}:{line} {what}")
        elif path.name == "CMakeLists.txt":
            try:
                text = _strip_cmake_comments(path.read_text(errors="replace"))
            except OSError:
                continue
            custom_msgs = custom_msgs or bool(_CUSTOM_MSGS_RE.search(text))
    if found and custom_msgs:
        found.append("CMakeLists.txt: find_package(custom_msgs)")
    return found


def pre_xrf2_message(project_dir: Path, evidence: list[str]) -> str:
    return (
        f"{project_dir.name}: this project is written for the framework before XRF2 ("
        + "; ".join(evidence)
        + "). XRF Lab builds XRF2 projects; that older framework (NativeBase / Native20Sim with "
        "preProc() and postProc(), messages in a custom_msgs package) is not supported. To bring "
        "it over: start from an XRF2 template (xrf new, or New project on the Projects page); "
        "derive your class from XenoFrt20Sim instead of Native20Sim (a 20-sim controller) or "
        "from XenoFrtRosIco instead of NativeBase; move the code of preProc() and postProc() "
        "into the state hooks (run() runs every cycle in RUN; initialising(), initialised(), "
        "stopping(), stopped(), paused() the others); and put the fields your custom_msgs "
        "messages carried into msg/Ros2Xeno.msg (host to loop, read as ros_msg) and "
        "msg/Xeno2Ros.msg (loop to host, written to xeno_msg). See docs/students/projects.md, "
        '"Projects of the framework before XRF2".'
    )


def detect_layout(project_dir: Path) -> Literal["xrf", "xrf2"]:
    cml = project_dir / "CMakeLists.txt"
    if not cml.exists():
        raise BuildError(f"{cml}: not found (a project needs a CMakeLists.txt)")
    evidence = pre_xrf2_evidence(project_dir)
    if evidence:
        raise BuildError(pre_xrf2_message(project_dir, evidence))
    text = _strip_cmake_comments(cml.read_text(errors="replace"))
    if "xrf_add_controller" in text or re.search(r"find_package\s*\(\s*XrfRt", text):
        return "xrf"
    if re.search(r"XenoRosFramework|ament_cmake|\brclcpp\b|ament_package", text):
        return "xrf2"
    # Neither: a plain CMake project. Build it as it is; the executable is found by the
    # CMake file API.
    return "xrf"


def _strip_cmake_comments(text: str) -> str:
    return "\n".join(line.split("#", 1)[0] for line in text.splitlines())


def _rel(p: Path, base: Path) -> str:
    try:
        return str(p.resolve().relative_to(base.resolve()))
    except ValueError:
        return str(p)


def _has_main(path: Path) -> bool:
    return bool(_MAIN_RE.search(path.read_text(errors="replace")))


def _walk(project: Path) -> list[Path]:
    out: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(project):
        dirnames[:] = sorted(d for d in dirnames if d not in _SKIP_DIRS and not d.startswith("."))
        out.extend(Path(dirpath) / f for f in sorted(filenames))
    return out


@dataclass
class _Xrf2Plan:
    name: str
    sources: list[Path]
    include_dirs: list[Path]
    msg_dir: Path
    twenty_sim: Path | None
    taken: list[str]
    left_out: dict[str, str]


def _xrf2_executable_name(cml_text: str, project: Path) -> str:
    m = re.search(r"add_executable\s*\(\s*([A-Za-z0-9_.+-]+)", _strip_cmake_comments(cml_text))
    name = m.group(1) if m and "$" not in m.group(1) else project.name
    name = re.sub(r"[^A-Za-z0-9_.+-]", "_", name) or "controller"
    return name


_CMAKE_TOKEN = re.compile(r'"((?:[^"\\]|\\.)*)"|([^\s()"#]+)|(\()|(\))|(#[^\n]*)')
_CMAKE_VAR = re.compile(r"\$\{([A-Za-z0-9_.+-]+)\}")


def _cmake_commands(text: str) -> Iterable[tuple[str, list[tuple[str, bool]]]]:
    """The commands of a CMakeLists.txt as (name, [(argument, quoted)]), comments dropped.
    Enough of CMake's syntax for the flat files XRF2 projects have."""
    name: str | None = None
    args: list[tuple[str, bool]] = []
    depth = 0
    pending: str | None = None
    for m in _CMAKE_TOKEN.finditer(text):
        quoted, word, lpar, rpar, comment = m.groups()
        if comment is not None:
            continue
        if name is None:
            if word is not None:
                pending = word
            elif lpar is not None and pending is not None:
                name, args, depth = pending.lower(), [], 1
            else:
                pending = None
            continue
        if lpar is not None:
            depth += 1
        elif rpar is not None:
            depth -= 1
            if depth == 0:
                yield name, args
                name, pending = None, None
        elif quoted is not None:
            args.append((quoted, True))
        elif word is not None:
            args.append((word, False))


@dataclass
class _CMakeRead:
    """What a project's own CMakeLists.txt compiles: per executable its source files, plus the
    include folders it names. ``complete`` is False when a source list used a variable that
    could not be evaluated (set by a find_package, a function, ...)."""

    executables: dict[str, list[Path]]
    include_dirs: list[Path]
    complete: bool
    framework_dirs: list[Path] = field(default_factory=list)


def _read_xrf2_cmake(project: Path, globs: bool = True) -> _CMakeRead:
    """``globs=False``: file(GLOB) and aux_source_directory() are not evaluated (their variables
    stay empty) -- enough to learn where the framework folder is, and a student's file(GLOB_RECURSE /*)
    never walks the appliance's disk outside the build's sandbox."""
    root = str(project)
    unknown: set[str] = set()
    executables: dict[str, list[Path]] = {}
    include_dirs: list[Path] = []
    framework_dirs: list[Path] = []
    incomplete = False
    keywords = {
        "PRIVATE",
        "PUBLIC",
        "INTERFACE",
        "BEFORE",
        "AFTER",
        "SYSTEM",
        "WIN32",
        "MACOSX_BUNDLE",
        "EXCLUDE_FROM_ALL",
        "STATIC",
        "SHARED",
        "OBJECT",
        "MODULE",
    }
    seen: set[Path] = set()

    def read(here: Path, variables: dict[str, list[str]], depth: int) -> None:
        """One CMakeLists.txt; ``here`` is its folder, which relative paths in it are relative to.
        add_subdirectory() reads the sub-folder's file with a copy of the variables (CMake gives
        a sub-directory its own scope)."""
        nonlocal incomplete
        cml = here / "CMakeLists.txt"
        if depth > 8 or cml.resolve() in seen or not cml.is_file():
            return
        seen.add(cml.resolve())
        text = cml.read_text(errors="replace")
        variables = dict(variables)
        variables["CMAKE_CURRENT_SOURCE_DIR"] = variables["CMAKE_CURRENT_LIST_DIR"] = [str(here)]

        def expand(arg: str, quoted: bool) -> list[str]:
            def sub(m: re.Match) -> str:
                if m.group(1) not in variables:
                    unknown.add(m.group(1))
                    return ""
                return ";".join(variables[m.group(1)])

            value = _CMAKE_VAR.sub(sub, arg)
            return [value] if quoted else [v for v in value.split(";") if v]

        def paths(values: list[str]) -> list[Path]:
            out = []
            for v in values:
                p = Path(v)
                out.append((p if p.is_absolute() else here / p).resolve())
            return out

        for name, raw in _cmake_commands(text):
            values: list[str] = []
            before = set(unknown)
            for arg, quoted in raw:
                values.extend(expand(arg, quoted))
            new_unknown = unknown - before
            # Where the project says XRF2's framework is (set(locationFramework "../XRF2/XenoRosFramework/")):
            # XRF2 kept the project's messages there, in Common/XRF2_msgs/msg.
            for v in values:
                m = re.match(r"(.*?XenoRosFramework)(?:/|$)", v.replace("\\", "/"))
                if m:
                    d = Path(m.group(1))
                    d = (d if d.is_absolute() else here / d).resolve()
                    if d not in framework_dirs:
                        framework_dirs.append(d)
            if name == "project" and values:
                variables["PROJECT_NAME"] = [values[0]]
            elif name == "set" and values:
                rest = values[1:]
                if "CACHE" in rest:
                    rest = rest[: rest.index("CACHE")]
                variables[values[0]] = [v for v in rest if v != "PARENT_SCOPE"]
            elif name == "list" and len(values) >= 2:
                op, var, items = values[0].upper(), values[1], values[2:]
                cur = variables.setdefault(var, [])
                if op == "APPEND":
                    cur.extend(items)
                elif op == "REMOVE_ITEM":
                    variables[var] = [c for c in cur if c not in items]
                elif op == "FILTER" and len(items) >= 3 and items[1].upper() == "REGEX":
                    try:
                        rx = re.compile(items[2])
                    except re.error:
                        continue
                    keep = items[0].upper() == "INCLUDE"
                    variables[var] = [c for c in cur if bool(rx.search(c)) == keep]
            elif name == "file" and len(values) >= 2 and values[0].upper() in ("GLOB", "GLOB_RECURSE") and not globs:
                variables[values[1]] = []
            elif name == "file" and len(values) >= 2 and values[0].upper() in ("GLOB", "GLOB_RECURSE"):
                recurse = values[0].upper() == "GLOB_RECURSE"
                var, pats = values[1], values[2:]
                found: list[str] = []
                relative = None
                while pats and pats[0].upper() in (
                    "CONFIGURE_DEPENDS",
                    "LIST_DIRECTORIES",
                    "RELATIVE",
                    "FOLLOW_SYMLINKS",
                ):
                    word = pats.pop(0).upper()
                    if word in ("LIST_DIRECTORIES", "RELATIVE") and pats:
                        arg = pats.pop(0)
                        relative = arg if word == "RELATIVE" else relative
                for pat in pats:
                    base = Path(pat) if Path(pat).is_absolute() else here / pat
                    parent, pattern = base.parent, base.name
                    if parent.is_dir():
                        it = parent.rglob(pattern) if recurse else parent.glob(pattern)
                        found.extend(str(f) for f in sorted(it) if f.is_file())
                variables[var] = found if relative is None else [os.path.relpath(f, relative) for f in found]
            elif name == "aux_source_directory" and len(values) == 2 and not globs:
                variables[values[1]] = []
            elif name == "aux_source_directory" and len(values) == 2:
                d = paths([values[0]])[0]
                variables[values[1]] = (
                    [str(f) for f in sorted(d.glob("*")) if f.suffix in _CXX_SUFFIXES] if d.is_dir() else []
                )
            elif name in ("add_executable", "add_library") and values:
                if any(v in ("IMPORTED", "ALIAS", "INTERFACE") for v in values[1:2]):
                    continue
                if new_unknown:
                    incomplete = True
                if name == "add_executable":
                    executables.setdefault(values[0], []).extend(paths([v for v in values[1:] if v not in keywords]))
                else:  # a library of the project's own files is part of what gets linked
                    executables.setdefault("", []).extend(paths([v for v in values[1:] if v not in keywords]))
            elif name == "target_sources" and values:
                if new_unknown:
                    incomplete = True
                executables.setdefault(values[0], []).extend(paths([v for v in values[1:] if v not in keywords]))
            elif name in ("target_include_directories", "include_directories"):
                vals = values[1:] if name == "target_include_directories" else values
                include_dirs.extend(d for d in paths([v for v in vals if v not in keywords]) if d.is_dir())
            elif name == "add_subdirectory" and values:
                sub = Path(values[0])
                sub = (sub if sub.is_absolute() else here / sub).resolve()
                if _inside(sub, project.resolve()):
                    read(sub, variables, depth + 1)

    read(project, {v: [root] for v in ("CMAKE_SOURCE_DIR", "PROJECT_SOURCE_DIR")}, 0)
    return _CMakeRead(executables, include_dirs, complete=not incomplete, framework_dirs=framework_dirs)


_MSG_FILES = ("Ros2Xeno.msg", "Xeno2Ros.msg")


def _has_messages(d: Path) -> bool:
    return all((d / f).is_file() for f in _MSG_FILES)


def _xrf2_msgs_package(d: Path) -> bool:
    """``d`` is a ROS 2 package named xrf2_msgs (XRF2's Common/XRF2_msgs, or a student's copy)."""
    try:
        text = (d / "package.xml").read_text(errors="replace")
    except OSError:
        return False
    return re.search(r"<name>\s*xrf2_msgs\s*</name>", text) is not None


def find_xrf2_messages(
    project: Path, framework_dirs: Iterable[Path] = (), within: Path | None = None
) -> tuple[Path | None, list[Path]]:
    """Where an XRF2 project's Ros2Xeno.msg and Xeno2Ros.msg are, and the places looked at.

    An XRF2 controller package usually has no msg/ of its own: the messages are part of the
    xrf2_msgs package that XRF2 keeps in ``XenoRosFramework/Common/XRF2_msgs`` (the framework
    folder the project's CMakeLists.txt names, ``../XRF2`` or ``../ros2-xenomai4-framework``),
    built into the same ROS 2 workspace. So, in this order: the project's own msg/; the
    framework folders its CMakeLists.txt names; an xrf2_msgs package or an XRF2 framework copy
    next to the project or one or two levels up (the workspace's src/). With ``within`` (an
    uploaded source folder) nothing outside that folder is looked at: not the project folder's
    other versions, not another student's project."""
    project = project.resolve()
    bound = within.resolve() if within is not None else None
    looked: list[Path] = []

    def consider(d: Path) -> Path | None:
        d = d.resolve()
        if d in looked or (bound is not None and not _inside(d, bound)):
            return None
        looked.append(d)
        return d if _has_messages(d) else None

    candidates: list[Path] = [project / "msg"]
    candidates += [fw / "Common" / "XRF2_msgs" / "msg" for fw in framework_dirs]
    ancestors = [project.parent, project.parent.parent, project.parent.parent.parent]
    for anc in ancestors:
        if not anc.is_dir() or (bound is not None and not _inside(anc, bound)):
            continue
        try:
            children = sorted(
                c for c in anc.iterdir() if c.is_dir() and c.name not in _SKIP_DIRS and not c.name.startswith(".")
            )
        except OSError:
            continue
        for c in children:
            if c == project:
                continue
            if _xrf2_msgs_package(c):
                candidates.append(c / "msg")
            fw = c / "XenoRosFramework"
            if fw.is_dir():
                candidates.append(fw / "Common" / "XRF2_msgs" / "msg")
            for sub in (c / "Common" / "XRF2_msgs",):  # c is XenoRosFramework itself
                if sub.is_dir():
                    candidates.append(sub / "msg")
    for d in candidates:
        found = consider(d)
        if found is not None:
            return found, looked
    return None, looked


def _xrf2_default_sources(project: Path) -> list[Path]:
    """XRF2's own templates compile main.cpp, src/*.cpp (and the 20-sim controller/)."""
    out = [p for p in (project / "main.cpp", project / "src" / "main.cpp") if p.is_file()]
    src = project / "src"
    if src.is_dir():
        out.extend(p for p in sorted(src.iterdir()) if p.is_file() and p.suffix in _CXX_SUFFIXES and p not in out)
    return [p.resolve() for p in out]


def _inside(p: Path, folder: Path) -> bool:
    try:
        p.relative_to(folder)
        return True
    except ValueError:
        return False


def plan_xrf2(project: Path, msg_dir: Path | None = None) -> _Xrf2Plan:
    """Decide which files of an XRF2-layout project to compile, and why others are not.

    XRF2 compiled what the project's CMakeLists.txt names (its templates: main.cpp, src/*.cpp
    and the 20-sim controller/); so do we, read from that file. A .cpp it does not name (an old
    copy, a test program, a folder of other experiments) is left out, as XRF2 left it out; when
    the file cannot be read completely, XRF2's template selection is added to what was read."""
    project = project.resolve()
    cml_text = (project / "CMakeLists.txt").read_text(errors="replace")
    taken: list[str] = []
    left_out: dict[str, str] = {
        "CMakeLists.txt": "XRF2 build file (compiles ../XRF2/XenoRosFramework, links evl/rclcpp); "
        "replaced by a generated one that uses rt_core",
    }
    controller = project / "controller"
    twenty_sim: Path | None = None
    if controller.is_dir() and any(controller.glob("*_tokens.xml")):
        twenty_sim = controller

    read = _read_xrf2_cmake(project)
    files = _walk(project)
    in_project = set(p.resolve() for p in files)

    def own_sources(paths: Iterable[Path]) -> list[Path]:
        return [
            p
            for p in paths
            if p in in_project
            and p.suffix.lower() in _CXX_SUFFIXES
            and p.stem not in XRF2_FRAMEWORK_STEMS
            and not (twenty_sim is not None and _inside(p, twenty_sim.resolve()))
        ]

    # The controller executable: the one that compiles XRF2's framework (or has the project's
    # main); other executables of the package (a ROS 2 node, a test) are not the controller.
    exe_name, chosen = "", []
    candidates = {n: v for n, v in read.executables.items() if n}
    for n, srcs in candidates.items():
        if any(p.stem in XRF2_FRAMEWORK_STEMS for p in srcs) or any(_has_main(p) for p in own_sources(srcs)):
            exe_name, chosen = n, srcs
            break
    selected = own_sources(chosen) + own_sources(read.executables.get("", []))
    if not selected or not read.complete:
        selected += [p for p in _xrf2_default_sources(project) if p not in selected]
    selected = list(dict.fromkeys(selected))
    other_exes = {p: n for n, srcs in candidates.items() if n != exe_name for p in own_sources(srcs)}

    sources: list[Path] = []
    mains: list[Path] = []
    include_dirs: list[Path] = []
    for path in files:
        rel = _rel(path, project)
        parts = Path(rel).parts
        suffix = path.suffix.lower()
        if twenty_sim is not None and parts[0] == "controller":
            # xrf_add_controller(TWENTY_SIM) takes the model and common/ itself.
            if suffix in (".cpp", ".c", ".h", ".hpp"):
                if path.name.startswith("test_") and suffix in (".cpp", ".c"):
                    left_out[rel] = "20-sim test program with its own main()"
                elif len(parts) <= 2 or parts[1] == "common":
                    taken.append(rel)
                else:
                    left_out[rel] = "not in the 20-sim folder or its common/"
            elif path.name.endswith("_tokens.xml"):
                taken.append(rel)
            else:
                left_out[rel] = "20-sim side file; not compiled"
            continue
        if path.stem in XRF2_FRAMEWORK_STEMS and suffix in (".cpp", ".hpp", ".h", ".c"):
            left_out[rel] = "XRF2 framework file; rt_core provides this class"
            continue
        if path.name == "package.xml":
            left_out[rel] = "ROS 2 package manifest; not used with rt_core"
        elif suffix == ".py":
            left_out[rel] = (
                "script (XRF2's token extraction is done by xrf_add_controller)"
                if "token" in path.name.lower()
                else "script; not part of the controller"
            )
        elif suffix in _CXX_SUFFIXES:
            resolved = path.resolve()
            if resolved not in selected:
                left_out[rel] = (
                    f"compiled into {other_exes[resolved]}, not the controller"
                    if resolved in other_exes
                    else "not compiled by the project's CMakeLists.txt (XRF2 built main.cpp, "
                    "src/*.cpp, controller/ and the files it names)"
                )
            elif path.name.startswith("test_") and _has_main(path):
                left_out[rel] = "test program with its own main()"
            else:
                if _has_main(path):
                    mains.append(path)
                sources.append(path)
    if len(mains) > 1:
        # XRF2 projects have one main.cpp; keep it and leave any other program out.
        keep = next((m for m in mains if m.name == "main.cpp"), None)
        if keep is None:
            raise BuildError(
                "several files define main(): "
                + ", ".join(_rel(m, project) for m in mains)
                + "; cannot tell which one is the controller"
            )
        for m in mains:
            if m != keep:
                sources.remove(m)
                left_out[_rel(m, project)] = f"has its own main(); {_rel(keep, project)} is the program"
    if not mains:
        raise BuildError(f"{project}: no C++ file defines main() (XRF2 projects have main.cpp or src/main.cpp)")
    for s in sources:
        taken.append(_rel(s, project))

    # Header folders: the ones the CMakeLists names, include/, and the folders of the compiled
    # files' headers; never a folder of XRF2 framework copies (rt_core's headers come first
    # anyway, see _write_xrf2_wrapper).
    def framework_folder(d: Path) -> bool:
        return any(f.stem in XRF2_FRAMEWORK_STEMS for f in d.glob("*.h*"))

    candidates_dirs = [d for d in read.include_dirs if _inside(d, project)]
    inc = project / "include"
    if inc.is_dir():
        candidates_dirs.insert(0, inc)
    candidates_dirs += [s.parent for s in sources]
    for d in candidates_dirs:
        d = d.resolve()
        if (
            d not in include_dirs
            and not (twenty_sim is not None and _inside(d, twenty_sim.resolve()))
            and (d == inc.resolve() or not framework_folder(d))
        ):
            include_dirs.append(d)
    for path in files:
        rel = _rel(path, project)
        if (
            path.suffix.lower() in (".h", ".hpp", ".hh")
            and rel not in left_out
            and path.stem not in XRF2_FRAMEWORK_STEMS
            and not Path(rel).parts[0] == "controller"
            and any(_inside(path.resolve(), d) for d in include_dirs)
        ):
            taken.append(rel)

    if msg_dir:
        mdir = Path(msg_dir).resolve()
    else:
        found, looked = find_xrf2_messages(project, read.framework_dirs)
        if found is None:
            raise BuildError(_no_xrf2_messages(looked, project, read.framework_dirs))
        mdir = found
    for f in _MSG_FILES:
        if (mdir / f).exists():
            taken.append(_rel(mdir / f, project))
    name = re.sub(r"[^A-Za-z0-9_.+-]", "_", exe_name) if exe_name and "$" not in exe_name else ""
    return _Xrf2Plan(
        name or _xrf2_executable_name(cml_text, project),
        sources,
        include_dirs,
        mdir,
        twenty_sim,
        sorted(set(taken)),
        dict(sorted(left_out.items())),
    )


_XRF2_CLASS_RE = re.compile(r"\b(XenoFrtRosIco|XenoFrt20Sim|XenoFrtLoop)\b")


def _is_framework_copy(d: Path) -> bool:
    """XRF2's own folder (XRF2/, ros2-xenomai4-framework/: it holds XenoRosFramework/ and the
    Template/ projects that come with it), or XenoRosFramework itself."""
    return d.name == "XenoRosFramework" or (d / "XenoRosFramework").is_dir()


def _uses_xrf2(package: Path) -> bool:
    try:
        cml = (package / "CMakeLists.txt").read_text(errors="replace")
    except OSError:
        return False
    if "XenoRosFramework" in _strip_cmake_comments(cml):
        return True
    for f in _walk(package):
        if f.suffix.lower() in _CXX_SUFFIXES + (".h", ".hpp") and f.stem not in XRF2_FRAMEWORK_STEMS:
            try:
                if _XRF2_CLASS_RE.search(f.read_text(errors="replace")):
                    return True
            except OSError:
                continue
    return False


def find_xrf2_controllers(folder: Path, depth: int = 4) -> list[Path]:
    """The XRF2 controller packages in a ROS 2 workspace (or its src/): the folders with a
    CMakeLists.txt that compile XRF2's framework or whose code derives from its loop classes.
    Other packages (a vision node, a message package, the simulator) and the XRF2 framework copy
    with its Template/ folders are not controllers."""
    found: list[Path] = []

    def visit(d: Path, level: int) -> None:
        if level > depth or _is_framework_copy(d):
            return
        if level > 0 and (d / "CMakeLists.txt").is_file():
            if _uses_xrf2(d):
                found.append(d)
            return  # a package's sub-folders are its own business
        try:
            subs = sorted(
                c for c in d.iterdir() if c.is_dir() and c.name not in _SKIP_DIRS and not c.name.startswith(".")
            )
        except OSError:
            return
        for c in subs:
            visit(c, level + 1)

    visit(folder, 0)
    return found


# ---------------------------------------------------------------------------------------
# where the project and its messages are: the one definition `xrf build`, the upload check,
# the project pages, `xrf upload` and the ROS 2 interface package all use


@dataclass(frozen=True)
class ProjectSource:
    """What a folder (a project, or a whole ROS 2 workspace) builds: the controller package
    ``project``, its ``layout``, and the folder ``msg_dir`` holding Ros2Xeno.msg / Xeno2Ros.msg."""

    folder: Path
    project: Path
    layout: Literal["xrf", "xrf2"]
    msg_dir: Path
    looked: tuple[Path, ...] = ()


def _shown(p: Path, base: Path) -> str:
    """``p`` as the student knows it: relative to the folder they gave (``../XRF2/...`` too)."""
    rel = os.path.relpath(p, base)
    return "." if rel == "." else rel


def controller_folder(folder: Path | str, log: Log | None = None) -> Path:
    """The controller package of ``folder``: the folder itself when it has a CMakeLists.txt, else
    (a ROS 2 workspace as XRF2 students keep it: src/XRF2, src/<controller>, other nodes) the one
    package below it that uses XRF2's loop."""
    folder = Path(folder).resolve()
    if (folder / "CMakeLists.txt").is_file():
        return folder
    controllers = find_xrf2_controllers(folder)
    if len(controllers) > 1:
        raise BuildError(
            f"{folder.name}: no CMakeLists.txt here, and several XRF2 controller packages below it ("
            + ", ".join(_shown(c, folder) for c in controllers)
            + "); build (or upload) the folder of the one you mean"
        )
    if not controllers:
        for cml in sorted(folder.glob("*/CMakeLists.txt")) + sorted(folder.glob("*/*/CMakeLists.txt")):
            # A workspace of the framework before XRF2: say that, not "no controller".
            evidence = pre_xrf2_evidence(cml.parent)
            if evidence:
                raise BuildError(pre_xrf2_message(cml.parent, evidence))
        raise BuildError(
            "missing CMakeLists.txt: none at the top of the folder and no XRF2 controller "
            "package (a folder with a CMakeLists.txt whose code uses XenoFrtLoop / "
            "XenoFrtRosIco) below it. Start from a template (xrf new, or New project in "
            "the dashboard), or give the ROS 2 workspace with the controller in it."
        )
    if log is not None:
        log(f"{folder}: a ROS 2 workspace; building its XRF2 controller package {_shown(controllers[0], folder)}")
    return controllers[0]


def _no_xrf2_messages(
    looked: Iterable[Path], base: Path, framework_dirs: Iterable[Path] = (), within: Path | None = None
) -> str:
    text = (
        "Ros2Xeno.msg and Xeno2Ros.msg not found. XRF2 kept them in its xrf2_msgs package "
        "(XenoRosFramework/Common/XRF2_msgs/msg); upload the project together with the XRF2 "
        "folder it names (the whole workspace), or copy the two files into the project's msg/ "
        "folder. Looked in: " + ", ".join(_shown(d, base) for d in looked)
    )
    if within is not None:
        outside = [d for d in framework_dirs if not _inside(d.resolve(), within.resolve())]
        if outside:
            text += (
                "; the CMakeLists.txt names "
                + ", ".join(_shown(d, base) for d in outside)
                + ", which is not in the upload"
            )
    return text


def locate_project(folder: Path | str, within: Path | str | None = None, log: Log | None = None) -> ProjectSource:
    """Where the controller of ``folder`` and its messages are, or BuildError saying what is
    missing and where it looked (paths relative to ``folder``).

    An XRF Lab project keeps its messages in msg/. An XRF2 project: see find_xrf2_messages (its
    own msg/, the framework folder its CMakeLists.txt names, an xrf2_msgs package or XRF2 copy
    next to it or up to the workspace). ``within`` bounds the search (an uploaded source folder:
    nothing outside it is read)."""
    folder = Path(folder).resolve()
    bound = Path(within).resolve() if within is not None else None
    project = controller_folder(folder, log)
    layout = detect_layout(project)
    if layout == "xrf":
        msg_dir = project / "msg"
        missing = [_shown(msg_dir / f, folder) for f in _MSG_FILES if not (msg_dir / f).is_file()]
        if missing:
            raise BuildError(
                "missing " + ", ".join(missing) + " (an XRF Lab project keeps its messages in "
                f"msg/). Looked in: {_shown(msg_dir, folder)}"
            )
        return ProjectSource(folder, project, layout, msg_dir, (msg_dir,))
    framework_dirs = _read_xrf2_cmake(project, globs=False).framework_dirs
    found, looked = find_xrf2_messages(project, framework_dirs, bound)
    if found is None:
        raise BuildError(_no_xrf2_messages(looked, folder, framework_dirs, bound))
    return ProjectSource(folder, project, layout, found, tuple(looked))


def _cmake_quote(p: Path | str) -> str:
    s = str(p).replace("\\", "/")
    return '"' + s.replace('"', '\\"') + '"'


def _write_xrf2_wrapper(plan: _Xrf2Plan, project: Path, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Generated by xrflab.build for the XRF2-layout project",
        f"#   {project}",
        "# Its own CMakeLists.txt builds against XRF2 (ament, rclcpp, evl); this one builds the",
        "# same C++ files, unchanged, against rt_core. Do not edit: it is rewritten every build.",
        "cmake_minimum_required(VERSION 3.16)",
        f"project({re.sub(r'[^A-Za-z0-9_]', '_', plan.name)}_xrf LANGUAGES C CXX)",
        "find_package(XrfRt REQUIRED)",
        f"xrf_add_controller({plan.name}",
        "  SOURCES " + " ".join(_cmake_quote(s) for s in plan.sources),
    ]
    if plan.include_dirs:
        lines.append("  INCLUDE_DIRS " + " ".join(_cmake_quote(d) for d in plan.include_dirs))
    lines.append(f"  MSG_DIR {_cmake_quote(plan.msg_dir)}")
    if plan.twenty_sim:
        lines.append(f"  TWENTY_SIM {_cmake_quote(plan.twenty_sim)}")
    lines.append(")")
    # rt_core's headers before the project's folders: a copy of an XRF2 framework header kept
    # next to the student's own (include/IcoIo.hpp, configuration.h) must not replace rt_core's.
    lines += [
        "get_target_property(_xrf_rt_includes XrfRt::xrf_rt INTERFACE_INCLUDE_DIRECTORIES)",
        f"target_include_directories({plan.name} BEFORE PRIVATE ${{_xrf_rt_includes}})",
    ]
    text = "\n".join(lines) + "\n"
    target = dest / "CMakeLists.txt"
    # Unchanged content keeps its timestamp, so an incremental build does not reconfigure.
    if not target.exists() or target.read_text() != text:
        target.write_text(text)


# ---------------------------------------------------------------------------------------
# finding the executable


def _controller_records(build_dir: Path) -> list[dict]:
    out = []
    for f in sorted((build_dir / "xrf_controllers").glob("*.json")):
        try:
            out.append(json.loads(f.read_text()))
        except json.JSONDecodeError as exc:
            raise BuildError(
                f"{f}: unreadable controller record ({exc}); is a path with a quote or backslash involved?"
            ) from exc
    return out


_FILE_API_QUERY = Path(".cmake/api/v1/query/client-xrflab/query.json")


def _write_file_api_query(build_dir: Path) -> None:
    q = build_dir / _FILE_API_QUERY
    q.parent.mkdir(parents=True, exist_ok=True)
    q.write_text(json.dumps({"requests": [{"kind": "codemodel", "version": 2}]}))


def _executables_from_file_api(build_dir: Path) -> list[Path]:
    reply = build_dir / ".cmake/api/v1/reply"
    indexes = sorted(reply.glob("index-*.json"))
    if not indexes:
        return []
    index = json.loads(indexes[-1].read_text())
    resp = index.get("reply", {}).get("client-xrflab", {}).get("query.json", {})
    cm = next((r for r in resp.get("responses", []) if r.get("kind") == "codemodel"), None)
    if not cm:
        return []
    codemodel = json.loads((reply / cm["jsonFile"]).read_text())
    exes: list[Path] = []
    for conf in codemodel.get("configurations", [])[:1]:
        for t in conf.get("targets", []):
            target = json.loads((reply / t["jsonFile"]).read_text())
            if target.get("type") == "EXECUTABLE":
                for a in target.get("artifacts", []):
                    p = Path(a["path"])
                    exes.append(p if p.is_absolute() else build_dir / p)
    return exes


def _find_executable(build_dir: Path) -> tuple[Path, dict | None]:
    records = _controller_records(build_dir)
    if len(records) == 1:
        return Path(records[0]["executable"]), records[0]
    if len(records) > 1:
        raise BuildError(
            "the project defines several controllers ("
            + ", ".join(r["target"] for r in records)
            + "); one project, one controller"
        )
    exes = _executables_from_file_api(build_dir)
    if len(exes) == 1:
        return exes[0], None
    if not exes:
        raise BuildError("the project builds no executable (call xrf_add_controller())")
    raise BuildError(
        "the project builds several executables ("
        + ", ".join(str(e) for e in exes)
        + "); use xrf_add_controller() for the controller"
    )


# ---------------------------------------------------------------------------------------
# the build


def _xrfrt_config_dir(prefix: Path) -> Path:
    """Where rt_core's install put XrfRtConfig.cmake (lib/ or lib64/, by platform)."""
    found = sorted(prefix.glob("lib*/cmake/XrfRt/XrfRtConfig.cmake"))
    if not found:
        raise BuildError(f"rt_core install at {prefix} has no XrfRtConfig.cmake", "")
    return found[0].parent


def build_project(
    project_dir: Path | str,
    build_dir: Path | str | None = None,
    log: Log = print,
    msg_dir: Path | str | None = None,
    within: Path | str | None = None,
) -> BuildResult:
    """Configure and build a student project against rt_core; return what was built.

    ``build_dir`` defaults to ``<project>/build``. ``msg_dir`` overrides where Ros2Xeno.msg and
    Xeno2Ros.msg come from (the project's ``msg/`` otherwise; for an XRF2 project, where
    locate_project finds them). ``within``: see locate_project (the appliance's uploaded source).
    """
    given = Path(project_dir).resolve()
    if not given.is_dir():
        raise BuildError(f"{given}: project folder not found")
    build = Path(build_dir).resolve() if build_dir else given / "build"
    # A whole ROS 2 workspace as XRF2 students keep it builds its controller package.
    project = controller_folder(given, log)
    layout = detect_layout(project)
    if layout == "xrf2" and not msg_dir:
        msg_dir = locate_project(given, within).msg_dir
    prefix = ensure_rt_core(log)

    plan: _Xrf2Plan | None = None
    if layout == "xrf2":
        plan = plan_xrf2(project, Path(msg_dir) if msg_dir else None)
        log("XRF2-layout project: building its files unchanged against rt_core")
        for t in plan.taken:
            log(f"  taken:    {t}")
        for f, why in plan.left_out.items():
            log(f"  left out: {f}: {why}")
        source = build / "xrf2-wrapper"
        _write_xrf2_wrapper(plan, project, source)
        binary = build / "cmake"
    else:
        source = project
        binary = build
    binary.mkdir(parents=True, exist_ok=True)
    _drop_foreign_cache(binary, log)
    _write_file_api_query(binary)

    cmd = [
        "cmake",
        "-S",
        str(source),
        "-B",
        str(binary),
        *_generator_args(binary),
        "-DCMAKE_BUILD_TYPE=Release",
        f"-DCMAKE_PREFIX_PATH={prefix}",
        # Named explicitly: a reused build folder's cache would otherwise keep the XrfRt of an
        # older rt_core, whose shared-memory layout no longer matches the host's.
        f"-DXrfRt_DIR={_xrfrt_config_dir(prefix)}",
        f"-DPython3_EXECUTABLE={sys.executable}",
    ]
    if layout == "xrf":
        # Always passed: XRF_MSG_DIR lands in the cache, and an override from an earlier build
        # must not outlive the call that asked for it.
        cmd.append(f"-DXRF_MSG_DIR={Path(msg_dir).resolve() if msg_dir else ''}")
    _run(cmd, log, what="configure")
    _run(["cmake", "--build", str(binary), "--parallel", _jobs()], log, what="build")

    exe, record = _find_executable(binary)
    if not exe.exists():
        raise BuildError(f"{exe}: the build finished but the executable is missing")

    taken: list[str]
    left_out: dict[str, str]
    twenty: dict | None = None
    if record and record.get("twenty_sim"):
        twenty = dict(record["twenty_sim"])
        for k in ("folder", "tokens_file"):
            twenty[k] = _rel(Path(twenty[k]), project)
    if plan is not None:
        taken, left_out = plan.taken, plan.left_out
    elif record:
        taken = sorted(_rel(Path(s), project) for s in record["sources"])
        left_out = {
            _rel(Path(s), project): "20-sim test program with its own main()"
            for s in record.get("left_out_test_programs", [])
        }
    else:
        taken, left_out = [], {}
    log(f"built {exe}")
    return BuildResult(
        executable=exe, build_dir=build, layout=layout, taken=taken, left_out=left_out, twenty_sim=twenty
    )


def _main(argv: list[str]) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="Build an XRF Lab (or XRF2) controller project.")
    ap.add_argument("project")
    ap.add_argument("--build-dir")
    ap.add_argument("--msg-dir")
    a = ap.parse_args(argv)
    try:
        r = build_project(a.project, a.build_dir, msg_dir=a.msg_dir)
    except BuildError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        return 1
    print(
        json.dumps(
            {
                "executable": str(r.executable),
                "layout": r.layout,
                "taken": r.taken,
                "left_out": r.left_out,
                "twenty_sim": r.twenty_sim,
            },
            indent=2,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
